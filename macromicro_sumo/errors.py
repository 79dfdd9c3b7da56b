"""The one exception type that reaches users as a one-line message."""


class UserError(Exception):
    """Bad input or an unusable file: the CLI prints ``error: <message>`` and exits 2.

    Messages name the file, the field and the accepted range, so the user can fix the
    input without reading a traceback.
    """
