"""Qt-free events for the workspace model (napari's ``EmitterGroup``/``Event`` in miniature).

The workspace model (:mod:`app.model.state`) is plain Python: it declares its events here and
emits them after each change; widgets subscribe with :meth:`Event.connect`. Nothing here
imports Qt, so the model can be driven and tested without a display.

- Bound methods are held by weak reference (as napari does), so a subscribed widget can be
  deleted without disconnecting first; a callback whose Qt object is already deleted
  (``RuntimeError: ... already deleted``) is dropped at the next emission.
- :meth:`Event.blocked` is the re-entry guard for two-way bindings (a slider that writes the
  model and follows it).
- Emission is synchronous and must happen on the GUI thread (results from worker threads
  arrive there through Qt's queued signals before they touch the model).

Usage::

    events = EmitterGroup(points=(), surface=(), edited=("what",))
    events.points.connect(view.update)
    events.edited.emit("points")
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["Event", "EmitterGroup"]


class Event:
    """One event type: ``connect(callback)``, ``emit(*args)``, ``disconnect(callback)``."""

    __slots__ = ("name", "args", "_callbacks", "_blocked")

    def __init__(self, name: str, args: tuple[str, ...] = ()):
        self.name = name
        self.args = args
        self._callbacks: list[tuple[Any, Callable[..., Any] | None]] = []
        self._blocked = 0

    def connect(self, callback: Callable[..., Any]) -> Callable[..., Any]:
        """Call ``callback(*args)`` at each emission (bound methods: weakly held)."""
        if hasattr(callback, "__self__") and hasattr(callback, "__func__"):
            ref = weakref.WeakMethod(callback)
            self._callbacks.append((ref, None))
        else:
            self._callbacks.append((None, callback))
        return callback

    def disconnect(self, callback: Callable[..., Any] | None = None) -> None:
        """Remove ``callback`` (all callbacks if None); unknown callbacks are ignored."""
        if callback is None:
            self._callbacks.clear()
            return
        self._callbacks = [(ref, fn) for ref, fn in self._callbacks
                           if (fn if ref is None else ref()) != callback]

    def emit(self, *args: Any) -> None:
        if self._blocked:
            return
        dead = False
        for ref, fn in list(self._callbacks):
            target = fn if ref is None else ref()
            if target is None:
                dead = True
                continue
            try:
                target(*args)
            except RuntimeError as exc:          # a Qt widget deleted on the C++ side
                if "already deleted" not in str(exc):
                    raise
                self.disconnect(target)
        if dead:
            self._callbacks = [(ref, fn) for ref, fn in self._callbacks
                               if ref is None or ref() is not None]

    __call__ = emit

    @contextmanager
    def blocked(self) -> Iterator[None]:
        """No emission inside the ``with`` block (re-entry guard)."""
        self._blocked += 1
        try:
            yield
        finally:
            self._blocked -= 1

    def __len__(self) -> int:
        return len(self._callbacks)

    def __repr__(self) -> str:
        return f"<Event {self.name}({', '.join(self.args)}): {len(self)} callbacks>"


class EmitterGroup:
    """A named set of :class:`Event` s: ``EmitterGroup(points=(), edited=("what",))``."""

    def __init__(self, **events: tuple[str, ...]):
        self._names = tuple(events)
        for name, args in events.items():
            setattr(self, name, Event(name, tuple(args)))

    def __iter__(self) -> Iterator[Event]:
        return (getattr(self, name) for name in self._names)

    @contextmanager
    def blocked(self) -> Iterator[None]:
        """Block every event of the group."""
        for event in self:
            event._blocked += 1
        try:
            yield
        finally:
            for event in self:
                event._blocked -= 1
