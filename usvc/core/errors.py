"""One exception type for every user-facing input problem, so stages can print one line."""


class UsvcError(Exception):
    """Bad input or a degenerate scene: the message names the file, scene or key at fault."""


class SceneError(UsvcError):
    """A scene on disk cannot be imported as given."""


class SfmError(UsvcError):
    """Structure-from-motion could not produce a usable model."""


class KeypointError(UsvcError):
    """Keypoint scoring kept nothing or got unusable tracks."""
