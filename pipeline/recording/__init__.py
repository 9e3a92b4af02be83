"""The recording wing: the MCAP session format, its writer, reader and integrity chain."""
