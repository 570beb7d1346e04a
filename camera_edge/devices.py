"""Discovery of attached event cameras over USB (pyusb), for ``arena edge --list-devices``.

Known USB ids (from the vendors' udev rules and drivers):

* Prophesee: vendor 0x31F7 (Prophesee EVKs, recent firmware); Cypress FX3 vendor 0x04B4 with
  products 0x00F3-0x00F5 (Prophesee EVK2/3 and Century Arks SilkyEvCam, FX3 based). Opened
  through OpenEB's ``metavision_core`` as ``prophesee:[SERIAL]``.
* iniVation: Thesycon vendor 0x152A, products 0x8400-0x841F (DVS128, DAVIS, DVXplorer).
  Opened through ``dv-processing`` as ``inivation:[NAME]``.
"""

from __future__ import annotations

import importlib.util
import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path


@dataclass
class Device:
    """An attached camera: maker, USB ids, bus address, the source URL and what opening it needs."""

    vendor: str
    vendor_id: int
    product_id: int
    bus: int
    address: int
    product: str
    url: str
    needs: str

    def describe(self) -> str:
        # product and serial come from the device (or a sysfs file): control characters in them
        # would move the cursor or recolour the terminal, so they are shown escaped
        return (f"{self.vendor:<10} {self.vendor_id:04x}:{self.product_id:04x} bus {self.bus:03d} "
                f"dev {self.address:03d}  {printable(self.product):<24} -> {printable(self.url)}  ({self.needs})")


def printable(text: str) -> str:
    """``text`` with each non-printable character (newline, ESC, NUL, ...) and backslash written
    as a Python escape (``\\n``, ``\\x1b``), so it shows as one inert line on a terminal."""
    return "".join(c if c.isprintable() and c != "\\" else repr(c)[1:-1] for c in text)


def identify(vendor_id: int, product_id: int) -> tuple[str, str] | None:
    """(vendor name, URL scheme) of a known event camera USB id, else None."""
    if vendor_id == 0x31F7 or (vendor_id == 0x04B4 and product_id in (0x00F3, 0x00F4, 0x00F5)):
        return "Prophesee", "prophesee:"
    if vendor_id == 0x152A and 0x8400 <= product_id <= 0x841F:
        return "iniVation", "inivation:"
    return None


def _needs(scheme: str) -> str:
    if scheme == "prophesee:":
        ok = importlib.util.find_spec("metavision_core") is not None
        return "ready (metavision_core found)" if ok else \
            "needs OpenEB's metavision_core (build OpenEB with Python bindings) and its udev rules"
    ok = importlib.util.find_spec("dv_processing") is not None
    return "ready (dv-processing found)" if ok else "needs pip install dv-processing and iniVation's udev rules"


#: Linux's USB device tree: read when libusb is missing (a fresh machine often lacks it)
SYSFS_USB = Path("/sys/bus/usb/devices")


#: the most bytes read of one sysfs attribute (they hold a few; a fake tree may hold more)
_SYSFS_READ_BYTES = 4096
#: a USB id as sysfs writes it: four hex digits
_USB_ID = re.compile(r"[0-9a-fA-F]{4}")


def _sysfs_text(d: Path, name: str, notes: list[str] | None = None) -> str:
    """The text of the attribute file ``d/name`` (stripped, at most 256 characters); "" if there
    is none. One that exists but cannot be read (no permission, a folder, a FIFO) also gives "",
    and a line saying so in ``notes`` (when given)."""
    try:
        # O_NONBLOCK: opening a FIFO planted in the tree would otherwise wait for a writer forever
        fd = os.open(d / name, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        return ""
    except OSError as exc:
        _note(notes, d, f"{name} cannot be read ({exc.strerror or exc})")
        return ""
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            _note(notes, d, f"{name} is not a file")
            return ""
        data = os.read(fd, _SYSFS_READ_BYTES)
    except OSError as exc:
        _note(notes, d, f"{name} cannot be read ({exc.strerror or exc})")
        return ""
    finally:
        os.close(fd)
    return data.decode(errors="replace").strip()[:256]


def _sysfs_id(d: Path, name: str, notes: list[str] | None) -> int | None:
    """The USB id in ``d/name``, or None: none there (not a device), or (noted) unreadable or
    not four hex digits (``int(.., 16)`` would take "-0003", "+3", "0x31f7", "31f7_0")."""
    text = _sysfs_text(d, name, notes)
    if _USB_ID.fullmatch(text):
        return int(text, 16)
    if text:
        _note(notes, d, f"{name} {text[:16]!r} is not a 4-digit hex USB id")
    return None


def _note(notes: list[str] | None, d: Path, what: str) -> None:
    if notes is not None:
        notes.append(f"USB entry {printable(d.name)} skipped: {what}")


def sysfs_devices(root: Path = SYSFS_USB, notes: list[str] | None = None) -> list[Device]:
    """Attached event cameras from Linux's sysfs USB tree (``idVendor``, ``idProduct``,
    ``busnum``, ``devnum``, ``product``, ``serial`` files of each device folder): no libusb
    needed. Folders that are not devices (interfaces: no ids) are passed over; entries whose ids
    cannot be read or are not four hex digits are passed over too, each with a line saying why in
    ``notes`` (when given); a tree that cannot be read raises RuntimeError."""
    try:
        folders = sorted(root.iterdir())
    except OSError as exc:
        raise RuntimeError(f"cannot list USB devices: {root} cannot be read ({exc})") from None
    out = []
    for d in folders:
        vid = _sysfs_id(d, "idVendor", notes)
        pid = _sysfs_id(d, "idProduct", notes) if vid is not None else None
        if pid is None:
            continue
        known = identify(vid, pid)
        if known is None:
            continue
        vendor, scheme = known
        try:
            bus, addr = int(_sysfs_text(d, "busnum") or 0), int(_sysfs_text(d, "devnum") or 0)
        except ValueError:
            bus = addr = 0
        out.append(Device(vendor, vid, pid, bus, addr, _sysfs_text(d, "product"),
                          scheme + _sysfs_text(d, "serial"), _needs(scheme)))
    return out


def list_devices(sysfs: Path = SYSFS_USB, notes: list[str] | None = None) -> list[Device]:
    """Attached event cameras, through pyusb; without a libusb backend, from Linux's ``sysfs``
    tree (entries passed over are described in ``notes``, see :func:`sysfs_devices`). Raises
    RuntimeError (saying what to install, or what cannot be read) if USB cannot be enumerated
    either way."""
    found, why = None, ""
    try:
        import usb.core
    except ImportError:
        why = "pyusb is not installed"
    else:
        try:
            found = list(usb.core.find(find_all=True))
        except usb.core.NoBackendError:
            why = "pyusb found no USB backend"
    if found is None:
        try:
            is_dir = sysfs.is_dir()
        except OSError as exc:   # is_dir() raises for a parent that cannot be searched (EACCES)
            raise RuntimeError(f"cannot list USB devices: {why} and {sysfs} cannot be read ({exc})") from None
        if is_dir:
            return sysfs_devices(sysfs, notes)
        raise RuntimeError(f"cannot list USB devices: {why} and there is no {sysfs} (no USB visible here, "
                           "e.g. a container): install libusb-1.0 (e.g. apt install libusb-1.0-0), "
                           "or run where the camera is plugged in")
    out = []
    for d in found:
        known = identify(d.idVendor, d.idProduct)
        if known is None:
            continue
        vendor, scheme = known
        try:
            product = d.product or ""
            serial = d.serial_number or ""
        except (ValueError, usb.core.USBError):  # no permission to read strings
            product, serial = "(no permission: install the udev rules)", ""
        out.append(Device(vendor, d.idVendor, d.idProduct, d.bus or 0, d.address or 0, product,
                          scheme + serial, _needs(scheme)))
    return out
