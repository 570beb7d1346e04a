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
        return (f"{self.vendor:<10} {self.vendor_id:04x}:{self.product_id:04x} bus {self.bus:03d} "
                f"dev {self.address:03d}  {self.product:<24} -> {self.url}  ({self.needs})")


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


def _sysfs_text(d: Path, name: str) -> str:
    try:
        return (d / name).read_text(errors="replace").strip()[:256]
    except OSError:
        return ""


def sysfs_devices(root: Path = SYSFS_USB) -> list[Device]:
    """Attached event cameras from Linux's sysfs USB tree (``idVendor``, ``idProduct``,
    ``busnum``, ``devnum``, ``product``, ``serial`` files of each device folder): no libusb
    needed. Folders that are not devices (interfaces, unreadable ids) are passed over; a tree that
    cannot be read raises RuntimeError."""
    try:
        folders = sorted(root.iterdir())
    except OSError as exc:
        raise RuntimeError(f"cannot list USB devices: {root} cannot be read ({exc})") from None
    out = []
    for d in folders:
        try:
            vid, pid = int(_sysfs_text(d, "idVendor"), 16), int(_sysfs_text(d, "idProduct"), 16)
        except ValueError:
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


def list_devices(sysfs: Path = SYSFS_USB) -> list[Device]:
    """Attached event cameras, through pyusb; without a libusb backend, from Linux's ``sysfs``
    tree. Raises RuntimeError (saying what to install) if USB cannot be enumerated either way."""
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
        if sysfs.is_dir():
            return sysfs_devices(sysfs)
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
