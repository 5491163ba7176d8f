"""The one exception type of the sorting package."""


class SortingError(ValueError):
    """Bad input to a sorting function (shape, values, options); one sentence says what."""
