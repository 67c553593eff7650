"""``manisplat-view``: the twin, an episode or new demonstrations in the browser (viser), and
``--video`` replays written with PyAV."""
