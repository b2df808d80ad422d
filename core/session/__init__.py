"""The session document (JSON, relative paths) and its crash recovery."""
