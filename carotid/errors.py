"""The one exception type that means "bad input": the CLI turns it into one line on stderr and exit 2."""


class CarotidError(Exception):
    """An input or parameter problem the user can fix; its message is shown as is."""
