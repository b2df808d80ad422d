"""SSM Studio desktop application (PySide6 + pyvistaqt): widgets and wiring over ``core``."""

from app.qtfix import guard_singletons as _guard_singletons

_guard_singletons()  # PySide6 6.12.0 emit() leaks references to True (see app/qtfix.py)
