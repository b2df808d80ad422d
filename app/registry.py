"""The main window's one registry of actions and menus, by id (issue 30).

Every feature of the window (navigation, file actions, editing, ...) creates its actions and
menus here and finds the others' by their id: never by a menu's visible text ("&View") or by
an entry's position (``menu.actions()[2]``), so that renaming or reordering a menu entry
cannot silently move another feature's entries. Menu ids are short words (``"file"``,
``"view"``); an entry's place is given relative to another id (``before="quit"``).

The window holds it as ``window.registry`` (``QWidget.actions()`` is already Qt's).
"""

from __future__ import annotations

from collections.abc import Callable

from PySide6.QtGui import QAction, QActionGroup, QKeySequence
from PySide6.QtWidgets import QMainWindow, QMenu, QMenuBar, QWidget


class ActionRegistry:
    """Actions and menus of ``window`` by id; ``registry["zoom-structure"]`` is an action."""

    def __init__(self, window: QWidget):
        self._window = window
        self._actions: dict[str, QAction] = {}
        self._menus: dict[str, QMenu] = {}
        self._menu_bar: QMenuBar | None = None

    # -- actions ---------------------------------------------------------------------------
    def add(self, action_id: str, text: str, slot: Callable | None = None, shortcut=None,
            tip: str = "", checkable: bool = False, checked: bool = False) -> QAction:
        """A new window-wide action (its shortcut works wherever the focus is in the window)."""
        if action_id in self._actions:
            raise ValueError(f"action id {action_id!r} is already registered")
        action = QAction(text, self._window)
        if shortcut is not None:
            action.setShortcut(QKeySequence(shortcut))
        if tip:
            action.setToolTip(tip)
            action.setStatusTip(tip)
        if checkable:
            action.setCheckable(True)
            action.setChecked(checked)
        if slot is not None:
            action.triggered.connect(slot)
        self._window.addAction(action)
        self._actions[action_id] = action
        return action

    def __getitem__(self, action_id: str) -> QAction:
        try:
            return self._actions[action_id]
        except KeyError:
            raise KeyError(f"no action {action_id!r} (registered: "
                           f"{', '.join(sorted(self._actions))})") from None

    def __contains__(self, action_id: str) -> bool:
        return action_id in self._actions

    def ids(self) -> list[str]:
        return list(self._actions)

    # -- menus -----------------------------------------------------------------------------
    def add_menu(self, menu_id: str, title: str, parent: str | None = None,
                 before: str | None = None) -> QMenu:
        """A menu in the menu bar (``parent`` None) or a submenu of menu ``parent``, placed
        before the entry ``before`` (an action or menu id; appended when None)."""
        if menu_id in self._menus:
            raise ValueError(f"menu id {menu_id!r} is already registered")
        container = self._bar() if parent is None else self.menu(parent)
        menu = QMenu(title, container)
        if before is None:
            container.addMenu(menu)
        else:
            container.insertMenu(self._entry(before), menu)
        self._menus[menu_id] = menu
        return menu

    def has_menu(self, menu_id: str) -> bool:
        return menu_id in self._menus

    def _bar(self) -> QMenuBar:
        """The window's menu bar, made here in Python. ``QMainWindow.menuBar()`` makes one in
        C++ on first call, and shiboken then looks its wrapper up by address: on a fresh
        machine (PySide6 6.x, full GUI suite) it once returned a stale wrapper of a deleted
        ``QSurface`` at the same address, and ``QMenu(title, bar)`` raised a TypeError."""
        if self._menu_bar is None:
            if not isinstance(self._window, QMainWindow):
                raise TypeError("top-level menus need a QMainWindow")
            self._menu_bar = QMenuBar(self._window)
            self._window.setMenuBar(self._menu_bar)
        return self._menu_bar

    def menu(self, menu_id: str) -> QMenu:
        try:
            return self._menus[menu_id]
        except KeyError:
            raise KeyError(f"no menu {menu_id!r} (registered: "
                           f"{', '.join(sorted(self._menus))})") from None

    def place(self, menu_id: str, *items: str | QAction | None, before: str | None = None,
              after: str | None = None) -> None:
        """Put entries (action ids, actions, or None for a separator) into menu ``menu_id``:
        appended, or before the entry ``before``, or right after the entry ``after``."""
        menu = self.menu(menu_id)
        anchor = None if before is None else self._entry(before)
        if after is not None:
            target, entries = self._entry(after), iter(menu.actions())
            for entry in entries:
                if entry is target:
                    anchor = next(entries, None)   # the entry after it (None: the last one)
                    break
        for item in items:
            if item is None:
                menu.insertSeparator(anchor) if anchor is not None else menu.addSeparator()
                continue
            action = self[item] if isinstance(item, str) else item
            menu.insertAction(anchor, action) if anchor is not None else menu.addAction(action)

    def separator(self, menu_id: str, entry_id: str, before: str | None = None) -> QAction:
        """A separator in menu ``menu_id`` that other entries can be placed before by id."""
        menu = self.menu(menu_id)
        action = menu.insertSeparator(self._entry(before)) if before is not None \
            else menu.addSeparator()
        if entry_id in self._actions:
            raise ValueError(f"action id {entry_id!r} is already registered")
        self._actions[entry_id] = action
        return action

    def _entry(self, entry_id: str) -> QAction:
        """The QAction that stands for entry ``entry_id`` in a menu (a submenu's menuAction)."""
        if entry_id in self._menus:
            return self._menus[entry_id].menuAction()
        return self[entry_id]


class SliceTools:
    """The slice views' tools, one at a time (navigate, draw, brush, ruler, ...): per tool a
    checkable action ``tool-<name>`` in ``registry``, its hint for the status bar. ``choose``
    is called with the tool's name when its action is triggered."""

    def __init__(self, registry: ActionRegistry, choose: Callable[[str], None]):
        self._registry = registry
        self._choose = choose
        self.group = QActionGroup(registry._window)
        self.actions: dict[str, QAction] = {}
        self.hints: dict[str, str] = {}

    def add(self, tools: dict[str, tuple[str, str, str]], menu_before: str | None = None,
            tips: bool = True) -> None:
        """Per tool ``name: (text, key, hint)`` its action, placed in the View menu (appended,
        or before the entry ``menu_before``) once that menu exists."""
        for tool, (text, key, hint) in tools.items():
            action = self._registry.add(f"tool-{tool}", text,
                                        lambda checked=False, t=tool: self._choose(t), key,
                                        hint if tips else "", checkable=True)
            self.group.addAction(action)
            self.actions[tool] = action
            self.hints[tool] = hint
            if self._registry.has_menu("view"):
                self._registry.place("view", action, before=menu_before)
