"""One validated TOML configuration for every stage of ``carotid run``.

Each section is one stage; its keys and defaults are the fields of that stage's
parameter dataclass, whose numpy-style docstring (``Attributes``) documents
units, so ``carotid config --show`` prints the effective values with their
documentation and nothing is written twice.  Unknown sections or keys and
values of the wrong type are errors, not silently ignored.
"""

from __future__ import annotations

import dataclasses
import inspect
import re
import tomllib
from pathlib import Path

from carotid.errors import CarotidError


def _segment_schema() -> type:
    from carotid.segment.segmentation import SegmentStageParameters

    return SegmentStageParameters


def _stage_schema(name: str):
    def schema() -> type:
        from carotid import stages

        return getattr(stages, name)

    return schema


# Keys whose values are files: relative paths in a TOML file are taken from the file's folder.
FILE_KEYS = (("simulate", "waveform"), ("simulate", "probes_file"))

# Config section -> callable returning the stage's parameter dataclass (imported lazily).
SCHEMAS = {
    "segment": _segment_schema,
    "centerlines": _stage_schema("CenterlineStageParameters"),
    "surface": _stage_schema("SurfaceStageParameters"),
    "mesh": _stage_schema("MeshStageParameters"),
    "simulate": _stage_schema("FlowStageParameters"),
}


def describe(schema: type) -> dict[str, str]:
    """Field name -> its description (one line) in the dataclass's ``Attributes`` docstring section."""
    lines = []
    for cls in schema.__mro__:  # a subclass documents its own fields only
        doc = inspect.getdoc(cls) or ""
        if "Attributes\n----------\n" in doc:
            lines += doc.split("Attributes\n----------\n", 1)[1].splitlines()
    out, names = {}, []
    for line in lines:
        header = re.match(r"^([A-Za-z_][\w, ]*) : (.+)$", line)
        if header:
            names = [n.strip() for n in header.group(1).split(",")]
        elif names and line.startswith("    "):
            for name in names:
                out[name] = f"{out.get(name, '')} {line.strip()}".strip()
        else:
            names = []
    return out


def _check_type(section: str, key: str, value, default):
    """``value`` converted to the type of ``default`` (int -> float allowed), or CarotidError."""
    where = f"[{section}] {key}"
    if isinstance(default, bool) or isinstance(value, bool):
        if not (isinstance(default, bool) and isinstance(value, bool)):
            raise CarotidError(f"config {where}: expected {type(default).__name__}, got {value!r}")
        return value
    if isinstance(default, float) and isinstance(value, (int, float)):
        return float(value)
    if default is None or isinstance(value, type(default)):
        return value
    raise CarotidError(f"config {where}: expected {type(default).__name__}, got {value!r}")


class Config:
    """Parameters of every stage: the defaults, overridden by a TOML file or a dict.

    Parameters
    ----------
    overrides : dict, optional
        ``{section: {key: value}}``; validated against the stages' parameter dataclasses.
    """

    def __init__(self, overrides: dict | None = None):
        self.sections = {name: dataclasses.asdict(schema()()) for name, schema in SCHEMAS.items()}
        for section, values in (overrides or {}).items():
            if section not in self.sections:
                raise CarotidError(f"config: unknown section [{section}] (known: {', '.join(self.sections)})")
            if not isinstance(values, dict):
                raise CarotidError(f"config: [{section}] must be a table of key = value")
            defaults = self.sections[section]
            for key, value in values.items():
                if key not in defaults:
                    raise CarotidError(f"config: unknown key '{key}' in [{section}] (known: {', '.join(defaults)})")
                defaults[key] = _check_type(section, key, value, defaults[key])
        for name, schema in SCHEMAS.items():  # the dataclasses' own range checks
            self.parameters(name, schema)

    @classmethod
    def from_toml(cls, path: str | Path) -> "Config":
        """Read and validate a TOML file; the files it names (``FILE_KEYS``) are relative to its folder."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise CarotidError(f"{path}: no such config file") from None
        except OSError as exc:
            raise CarotidError(f"{path}: cannot read the config file ({exc.strerror})") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise CarotidError(f"{path}: not valid TOML ({exc})") from None
        for section, key in FILE_KEYS:  # a file named in the config lies beside it, wherever the run starts
            table = data.get(section)
            value = table.get(key) if isinstance(table, dict) else None
            if isinstance(value, str) and value and not Path(value).is_absolute():
                table[key] = str(path.parent / value)
        return cls(data)

    def section(self, name: str) -> dict:
        """A copy of one section's effective values (an empty dict for a stage without parameters)."""
        return dict(self.sections.get(name, {}))

    def parameters(self, name: str, schema=None):
        """The section as its validated parameter dataclass."""
        schema = schema or SCHEMAS[name]
        params = schema()(**self.sections[name])
        return params.validate() if hasattr(params, "validate") else params

    def to_toml(self) -> str:
        """The effective configuration as TOML, each key commented with its documentation."""
        lines = []
        for name, values in self.sections.items():
            docs = describe(SCHEMAS[name]())
            lines.append(f"[{name}]")
            for key, value in values.items():
                comment = f"  # {docs[key]}" if key in docs else ""
                lines.append(f"{key} = {_toml_value(value)}{comment}")
            lines.append("")
        return "\n".join(lines)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)
