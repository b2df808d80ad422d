"""SSM Studio desktop application (PySide6 + pyvistaqt): widgets and wiring over ``core``."""
