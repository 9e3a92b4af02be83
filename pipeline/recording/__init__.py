"""The recording wing: the MCAP session format (``docs/recording.md``).

Modules, one job each: :mod:`~crossfield.recording.layout` (every topic,
schema, metadata and attachment name), :mod:`~crossfield.recording.codec`
(encoders and decoders), :mod:`~crossfield.recording.writer` (message
building and the sinks), :mod:`~crossfield.recording.recorder` (the observer
plugins), :mod:`~crossfield.recording.reader` (reading a file),
:mod:`~crossfield.recording.facts` (the session facts, one loader) and
:mod:`~crossfield.recording.integrity` (the integrity chain).
"""
