"""The ``satsweep`` command line: thin argparse subcommands over the typed API.

Every ``SatsweepError`` becomes one line on stderr (``satsweep: error: <file>: <problem>``) and
exit code 2; nothing is written for a run that fails on its input.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Callable, Sequence

from . import __version__
from .errors import SatsweepError

Handler = Callable[[argparse.Namespace], int]


# -- devices -----------------------------------------------------------------------------------
def _add_devices(sub) -> None:
    p = sub.add_parser(
        "devices",
        help="list OpenCL platforms/devices and whether each can build a kernel",
        description="List every OpenCL device with its memory and whether it builds and runs a "
        "trivial kernel, and show which one --device/SATSWEEP_DEVICE would select.",
    )
    p.add_argument("--device", default=None, help="auto|cpu|gpu|PLATFORM:DEVICE (default: $SATSWEEP_DEVICE or auto)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(handler=_cmd_devices)


def _cmd_devices(args: argparse.Namespace) -> int:
    from . import device as sdev

    devices = sdev.list_devices(check_build=True)
    selected = None
    select_error = None
    try:
        selected = sdev.select_device(args.device)
    except SatsweepError as exc:
        select_error = str(exc)
    if args.json:
        print(json.dumps({
            "devices": [d.as_dict() for d in devices],
            "selected": selected.spec if selected else None,
            "error": select_error,
        }, indent=2))
    else:
        if not devices:
            print("no OpenCL device found")
        for d in devices:
            mark = "*" if selected is not None and d.spec == selected.spec else " "
            build = "builds kernels" if d.can_build else f"CANNOT BUILD KERNELS ({d.build_error})"
            print(
                f"{mark} {d.spec:5s} {d.kind:5s} {d.platform_name} / {d.device_name}: "
                f"{d.global_mem_bytes / 2**30:.1f} GiB global, "
                f"{d.max_alloc_bytes / 2**30:.1f} GiB max alloc, {d.compute_units} CUs, {build}"
            )
        if selected is not None:
            print(f"selected: {selected.label}")
    if select_error:
        print(f"satsweep: error: {select_error}", file=sys.stderr)
        return 2
    return 0


# -- entry point -------------------------------------------------------------------------------
_COMMANDS = [_add_devices]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="satsweep",
        description="Satellite multi-view stereo: RPC images + an area of interest -> DSM.",
    )
    parser.add_argument("--version", action="version", version=f"satsweep {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in _COMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except SatsweepError as exc:
        print(f"satsweep: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("satsweep: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
