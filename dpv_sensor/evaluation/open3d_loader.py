"""Import Open3D on machines without the system libusb it links against.

The open3d-cpu wheel links libusb-1.0.so.0 (for RealSense support we never use). Debian images often
lack it, so we load the copy shipped by the `libusb-package` wheel first; the dynamic loader then
resolves open3d's dependency against the already-loaded library.
"""
from __future__ import annotations

import ctypes


def import_open3d():
    """Return the open3d module, preloading libusb from the libusb-package wheel when needed."""
    try:
        import open3d
        return open3d
    except ImportError as exc:
        if 'libusb' not in str(exc):
            raise
    import libusb_package
    path = libusb_package.get_library_path()
    if path is None:
        raise ImportError('open3d needs libusb-1.0.so.0 and libusb-package ships none for this platform')
    ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    import open3d
    return open3d
