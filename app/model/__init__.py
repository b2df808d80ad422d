"""The workspace's Qt-free model (napari's ``components/`` beside its ``_qt/``): the
structures, points and undo history (:mod:`.state`, :mod:`.history`), their events
(:mod:`.events`), the session/export logic (:mod:`.controllers`), the second image
(:mod:`.second_image`) and the DBS plan (:mod:`.planning`). Nothing here imports Qt or VTK
(``tests/test_workspace_model.py``); widgets and views subscribe to the events.
"""
