"""The one exception type for mistakes a user can fix (bad argument, file, shape)."""


class UserError(ValueError):
    """A problem with the user's input; the CLI prints it as one line and exits with status 2."""
