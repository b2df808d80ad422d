"""Snapshot undo/redo stacks, Qt-free: one implementation for the structures and the plan.

The owner gives two callables: ``snapshot()`` captures its current state (immutable values or
copies) and ``restore(snapshot)`` puts one back and emits the owner's events; ``changed()`` is
called when the stacks change (to enable or disable Undo/Redo).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

MAX_HISTORY = 200


class UndoHistory:
    """``checkpoint()`` before an undoable edit; ``undo()``/``redo()`` step through them."""

    def __init__(self, snapshot: Callable[[], Any], restore: Callable[[Any], None],
                 changed: Callable[[], None] = lambda: None, limit: int = MAX_HISTORY):
        self._snapshot, self._restore, self._changed = snapshot, restore, changed
        self.limit = int(limit)
        self._undo: list[Any] = []
        self._redo: list[Any] = []

    def checkpoint(self) -> None:
        """Record the current state as one undo step."""
        self.push(self._snapshot())

    def push(self, snapshot: Any) -> None:
        """Record ``snapshot`` (not the current state) as the newest undo step."""
        self._undo.append(snapshot)
        del self._undo[:-self.limit]
        self._redo.clear()
        self._changed()

    def can_undo(self) -> bool:
        return bool(self._undo)

    def can_redo(self) -> bool:
        return bool(self._redo)

    def undo(self) -> bool:
        if not self._undo:
            return False
        self._redo.append(self._snapshot())
        self._restore(self._undo.pop())
        return True

    def redo(self) -> bool:
        if not self._redo:
            return False
        self._undo.append(self._snapshot())
        self._restore(self._redo.pop())
        return True

    def clear(self) -> None:
        self._undo.clear()
        self._redo.clear()
        self._changed()
