"""Edit-menu commands of the main window that act on the active slice view or structure.

Each reads which view is active and where the cursor is from the window and changes the
Qt-free :class:`app.model.state.WorkspaceState`; the window's ``delete_point``,
``clear_active_slice`` and ``place_here`` delegate here.
"""

from __future__ import annotations


class EditCommands:
    """Point deletion, slice clearing and manual placement for main window ``window``."""

    def __init__(self, window):
        self.w = window

    def delete_point(self) -> None:
        """The point under the cursor, else the last point drawn on the active view's slice."""
        w, state = self.w, self.w.state
        view = w.workspace.views[w.active_view]
        if w.cursor_label.hover is not None:
            x, y = view.world_to_screen(w.cursor_label.hover)
            if view.delete_point_near(x, y):
                return
        here = view.points_here()
        if len(here) and not state.active.locked:
            state.active.remove_point(int(here[-1]))
        else:
            w.show_message(f"No point to delete on this {w.active_view} slice")

    def clear_active_slice(self) -> None:
        w = self.w
        view = w.workspace.views[w.active_view]
        removed = w.state.clear_slice(w.active_view, view.depth)
        w.show_message(f"Removed {removed} point(s) from the {w.active_view} slice")

    def place_here(self) -> None:
        """Move the active structure's model centre to the crosshair (then refit)."""
        w, state = self.w, self.w.state
        if state.active.model is None:
            w.show_message("Load a model first (File > Load model)")
            return
        w.refit.cancel(state.active)
        state.active.place_at(state.crosshair)
        if len(state.active.points):
            w.schedule_refit()
