"""One exception family for the whole project.

Every message names the input that is wrong and, where there is one, the fix. The CLI turns a
``CropCraftError`` into a single readable line and a non-zero exit code.
"""


class CropCraftError(Exception):
    """Base class of every error CropCraft raises on purpose."""


class ConfigError(CropCraftError, ValueError):
    """A parameter, preset or option is unknown or out of its range."""


class InputError(CropCraftError, ValueError):
    """An input file or array is missing, unreadable or malformed."""


class OutputError(CropCraftError, OSError):
    """An output location cannot be written."""


class GeometryError(CropCraftError, ValueError):
    """Geometry is degenerate or inconsistent (no faces, NaN vertices, ...)."""
