"""The one error type for bad scenes; messages name the problem and where it is."""


class SceneError(ValueError):
    """A scene, mesh or setting that nprt refuses, with a message meant for the user."""


class UnsafePath(SceneError):
    """A file reference that would leave the directory a scene is confined to (an upload):
    an absolute path, a `..` escape or a symlink pointing out. The service answers 400."""
