"""Device time per OpenCL kernel of one satsweep command.

    python tools/profile_kernels.py [--json PATH] -- reconstruct stack/*.tif --aoi ... --out DIR

Runs the command in this process as the `satsweep` command runs it (``cli.console_main``:
numpy's BLAS in one thread, so its products are the command's bit for bit) with profiling
enabled on every OpenCL command queue, then prints each kernel's device seconds (its launches'
events, end - start, summed), launches and share of the total, the largest first. It tells
which kernel a stage's time is in, on the real stage rather than a benchmark's case; compare
two runs on one machine at one hour only (PoCL's times vary by several percent from run to
run, and profiling itself costs a little).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path

# This checkout's satsweep first, not an installed one.
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


class KernelProfile:
    """While installed (a context manager), every command queue made is a profiling one and
    every kernel launch's event is kept; ``totals`` then gives each kernel's device seconds and
    launches. Queues made before it is installed are not profiled (their launches are skipped)."""

    def __init__(self) -> None:
        self.events: list[tuple[str, object]] = []
        self._saved = None

    def __enter__(self) -> KernelProfile:
        import pyopencl as cl  # noqa: PLC0415

        base_queue, base_call = cl.CommandQueue, cl.Kernel.__call__
        events = self.events

        class ProfilingQueue(base_queue):
            def __init__(self, context, device=None, properties=None):
                props = int(properties or 0) | cl.command_queue_properties.PROFILING_ENABLE
                super().__init__(context, device, properties=props)

        def call(kernel, queue, *args, **kwargs):
            event = base_call(kernel, queue, *args, **kwargs)
            if isinstance(queue, ProfilingQueue):
                events.append((kernel.function_name, event))
            return event

        self._saved = (base_queue, base_call)
        cl.CommandQueue = ProfilingQueue
        cl.Kernel.__call__ = call
        return self

    def __exit__(self, *exc) -> None:
        import pyopencl as cl  # noqa: PLC0415

        cl.CommandQueue, cl.Kernel.__call__ = self._saved

    def totals(self) -> dict[str, tuple[float, int]]:
        """{kernel name: (device seconds, launches)}, waiting for every kept launch."""
        out: dict[str, tuple[float, int]] = {}
        for name, event in self.events:
            event.wait()
            seconds = (event.profile.end - event.profile.start) * 1e-9
            total, launches = out.get(name, (0.0, 0))
            out[name] = (total + seconds, launches + 1)
        return out


def format_totals(totals: dict[str, tuple[float, int]]) -> list[str]:
    """Lines of a table of ``KernelProfile.totals``, the largest first."""
    whole = sum(s for s, _ in totals.values())
    lines = [f"device time {whole:.2f} s over {sum(n for _, n in totals.values())} launches"]
    for name, (seconds, launches) in sorted(totals.items(), key=lambda kv: -kv[1][0]):
        share = 100.0 * seconds / whole if whole > 0 else 0.0
        lines.append(f"  {name:34s} {seconds:9.3f} s {share:5.1f}% {launches:7d} launches")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, help="also write {kernel: [seconds, launches]}")
    parser.add_argument("command", nargs=argparse.REMAINDER,
                        help="the satsweep command and its arguments (after --)")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give the satsweep command to run, e.g. -- reconstruct ...")
    from satsweep import cli  # noqa: PLC0415  (it imports no numpy until it runs)

    # console_main sets these too, but pyopencl (the profile) imports numpy first.
    for name in cli.BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    with KernelProfile() as profile:
        status = cli.console_main(command)
    totals = profile.totals()
    print("\n".join(format_totals(totals)))
    if args.json is not None:
        from satsweep.io.atomic import atomic_output  # noqa: PLC0415

        with atomic_output(args.json) as tmp:  # a whole file or none
            Path(tmp).write_text(json.dumps({k: list(v) for k, v in totals.items()}, indent=1))
    return int(status or 0)


if __name__ == "__main__":
    sys.exit(main())
