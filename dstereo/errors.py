"""The one error type a user sees: its message names the file/parameter and what to do."""


class DstereoError(ValueError):
    """Bad input or configuration. The CLI prints the message on one line and exits 1."""
