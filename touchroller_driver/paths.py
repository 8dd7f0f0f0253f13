"""Where installed data lives: the ament index, then `sys.prefix/share`, then the source checkout."""
from __future__ import annotations

import sys
from pathlib import Path

PACKAGE = "touchroller_bringup"
_CHECKOUT = Path(__file__).resolve().parent.parent


def share_dir() -> Path:
    """The package's share directory (holds `launch/`, `config/`, `package.xml`)."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    except ImportError:
        pass
    else:
        try:
            return Path(get_package_share_directory(PACKAGE))
        except (PackageNotFoundError, LookupError, ValueError, OSError):  # OSError: AMENT_PREFIX_PATH unset
            pass
    prefix_share = Path(sys.prefix) / "share" / PACKAGE
    if (prefix_share / "config").is_dir():
        return prefix_share
    return _CHECKOUT


def config_path(*parts: str) -> Path:
    """A file under the package's `config/` folder, e.g. `config_path("scenes", "surface_mapping.yaml")`."""
    return share_dir() / "config" / Path(*parts)


def checkout_dir() -> Path:
    """The source checkout this code runs from (holds bench/, docs/); meaningful only in a checkout."""
    return _CHECKOUT

