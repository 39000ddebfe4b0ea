"""The one exception type for a user's mistake in a file, a config or an argument."""


class InputError(ValueError):
    """Bad user input: the message names the file, the line or row, the field, and the fix.

    A subclass of `ValueError`, so API callers can catch either. The command line
    turns it into a one-paragraph message and exit status 2.
    """

    def __init__(self, message: str, *, file: str | None = None, line: int | None = None,
                 field: str | None = None):
        where = []
        if file is not None:
            where.append(f"{file}")
        if line is not None:
            where.append(f"line {line}")
        if field is not None:
            where.append(f"field '{field}'")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)
        self.message = message  # without the location
        self.file = file
        self.line = line
        self.field = field
