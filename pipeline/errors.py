"""The one exception type the CLI turns into a one-line message and exit code 2."""


class UserError(Exception):
    """Bad input from the user: the message says what is wrong and what to do.

    Raise it with one sentence, e.g.
    ``UserError(f"{path}: environment map is 512x512, expected width = 2*height; resample it")``.
    Programming errors stay ordinary exceptions (with a traceback).
    """

    exit_code = 2
