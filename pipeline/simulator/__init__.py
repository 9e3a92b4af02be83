"""The station simulator: the oracle for the demo and the tests."""
