"""The session document (JSON, relative paths: document.py) and its crash recovery (recovery.py)."""
