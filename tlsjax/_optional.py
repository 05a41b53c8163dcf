"""Imports of the optional libraries (open3d, pye57, laspy) with messages that name the fix.

A Python package can be installed and still fail to import because a *system* library that its
compiled part links against is missing (open3d's wheel needs ``libusb-1.0.so.0``, ``libGL.so.1``
and ``libgomp.so.1`` on Linux). Telling the user to ``pip install`` again then sends them the
wrong way, so the message names the missing shared library and the Debian package that has it.
"""

from __future__ import annotations

import importlib
import re

#: Shared libraries the optional packages' wheels load, and the Debian/Ubuntu package of each.
SYSTEM_PACKAGES = {
    "libusb-1.0.so.0": "libusb-1.0-0",
    "libGL.so.1": "libgl1",
    "libEGL.so.1": "libegl1",
    "libgomp.so.1": "libgomp1",
    "libX11.so.6": "libx11-6",
    "libglib-2.0.so.0": "libglib2.0-0",
}

#: The pip extra of tlsjax that installs each optional package.
EXTRAS = {"open3d": "open3d", "pye57": "e57", "laspy": "las", "lazrs": "las"}


def missing_library_message(module: str, purpose: str, err: BaseException) -> str:
    """One line saying why ``module`` cannot be used and what installs it."""
    text = str(err)
    so = re.search(r"(lib[\w.+-]+\.so[\w.]*)", text)
    if so and ("cannot open shared object" in text or "No such file" in text):
        lib = so.group(1)
        pkg = SYSTEM_PACKAGES.get(lib)
        how = f"apt-get install -y {pkg}" if pkg else f"install the system package that has {lib}"
        return (
            f"{purpose} needs {module}, which is installed but cannot load the system library "
            f"{lib}: {how} (./scripts/setup does this when run as root)"
        )
    extra = EXTRAS.get(module, module)
    return (
        f"{purpose} needs the Python package {module}, which cannot be imported ({text}): "
        f"pip install 'tlsjax[{extra}]' (./scripts/setup installs it)"
    )


def require(module: str, purpose: str):
    """Import ``module`` or raise ImportError with :func:`missing_library_message`."""
    try:
        return importlib.import_module(module)
    except (ImportError, OSError) as err:  # OSError: a broken shared library
        raise ImportError(missing_library_message(module, purpose, err)) from None
