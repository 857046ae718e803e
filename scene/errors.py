"""The one error type for bad scenes; messages name the problem and where it is."""


class SceneError(ValueError):
    """A scene, mesh or setting that nprt refuses, with a message meant for the user."""
