"""The one exception type that means "bad input": the CLI turns it into one line on stderr and exit 2."""


class CarotidError(Exception):
    """An input or parameter problem the user can fix; its message is shown as is."""


class CarotidWarning(UserWarning):
    """Something the user should know that does not stop the run; the CLI shows it as one line on stderr."""


def check_ranges(section: str, values: object, ranges: dict[str, tuple[float, float]]) -> None:
    """Raise CarotidError for the first attribute of ``values`` outside its closed range.

    Parameters
    ----------
    section : str
        What the values parametrise, for the message ("mesh", "simulate"...).
    values : object
        Holds the checked attributes (a parameter dataclass).
    ranges : dict
        Attribute name -> (low, high), both included; NaN is outside every range.
    """
    for name, (low, high) in ranges.items():
        value = getattr(values, name)
        if not low <= value <= high:
            raise CarotidError(f"bad {section} parameter: {name} = {value} is outside [{low:g}, {high:g}]")
