"""The session report document (report.json) shared by the report implementations."""
