"""The one exception type of the dataset readers."""


class DatasetError(ValueError):
    """A dataset on disk is missing, malformed or inconsistent.

    The message names the offending file or folder and says how to fix it.
    """
