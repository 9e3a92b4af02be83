"""crossfield core: hook specs, plugin manager, data types, config, runner, recorder."""
