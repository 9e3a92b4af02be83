"""Built-in crossfield plugins, one module per implementation."""
