"""Time reading an AOI window from a large tiled or stripped, compressed scene.

    python tools/bench_read.py [--size 20000] [--window 1000] [--layout tiled|strips] [--keep DIR]

Writes a --size^2 uint16 scene (12-bit values, deflate, 512 px tiles or 16-row strips: the way
full scenes are often delivered or converted by GDAL) into a temporary folder, then times, in the
same run, ``satsweep.imageio.read_image`` of a --window^2 window at its centre (it decodes only the
tiles or strips that the window overlaps) against decoding the whole image and slicing it (what a
reader without windows does), and prints the ratio and the process's peak memory after each.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# This checkout's satsweep first, not an installed one (a run from another worktree measures
# that worktree's code).
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _scene(size: int) -> np.ndarray:
    """A smooth 12-bit field with a fine texture: compresses like an image, not like noise."""
    y = np.arange(size, dtype=np.float32)[:, None]
    x = np.arange(size, dtype=np.float32)[None, :]
    field = 2000.0 + 800.0 * np.sin(x / 97.0) * np.cos(y / 131.0)
    rng = np.random.default_rng(0)
    texture = rng.integers(0, 16, size=(size, size), dtype=np.uint16)
    return (field.astype(np.uint16) + texture) & 0x0FFF


def main(argv=None) -> int:
    import tifffile

    from satsweep.io.images import read_image
    from satsweep.pipeline.report import peak_memory_bytes

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=20000, help="scene width and height (px)")
    p.add_argument("--window", type=int, default=1000, help="window width and height (px)")
    p.add_argument("--layout", choices=("tiled", "strips"), default="tiled")
    p.add_argument("--keep", type=Path, default=None, help="write the scene here and keep it")
    p.add_argument("--make-only", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if not 1 <= args.window <= args.size:
        p.error("--window must be in [1, --size]")

    folder = args.keep or Path(tempfile.mkdtemp(prefix="satsweep-bench-read-"))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"scene_{args.size}_{args.layout}.tif"
    layout = {"tile": (512, 512)} if args.layout == "tiled" else {"rowsperstrip": 16}
    if args.make_only:
        tifffile.imwrite(path, _scene(args.size), compression="zlib", **layout)
        return 0
    t = time.perf_counter()
    if not path.exists():  # made by a child process, so that this one's peak memory is the reads'
        subprocess.run([sys.executable, __file__, "--make-only", "--size", str(args.size),
                        "--layout", args.layout, "--keep", str(folder)], check=True)
    print(f"scene {args.size}^2 uint16, {args.layout}, deflate: {path.stat().st_size / 2**20:.0f} MiB "
          f"on disk ({time.perf_counter() - t:.1f} s to make)")

    c = (args.size - args.window) // 2
    window = (c, c, c + args.window, c + args.window)
    t = time.perf_counter()
    part = read_image(path, window=window)
    t_window = time.perf_counter() - t
    peak_window = peak_memory_bytes()
    t = time.perf_counter()
    whole = tifffile.imread(path)[c:c + args.window, c:c + args.window]
    t_whole = time.perf_counter() - t
    peak_whole = peak_memory_bytes()
    if not np.array_equal(part, whole):
        print("MISMATCH: the window differs from the whole image's slice", file=sys.stderr)
        return 1

    def mib(b):
        return "n/a" if b is None else f"{b / 2**20:.0f} MiB"

    print(f"window {args.window}^2 at the centre: read_image {t_window:.3f} s "
          f"(peak memory so far {mib(peak_window)}); whole image decoded and sliced "
          f"{t_whole:.3f} s (peak {mib(peak_whole)}): {t_whole / t_window:.0f}x")
    if args.keep is None:
        path.unlink()
        os.rmdir(folder)
    return 0


if __name__ == "__main__":
    sys.exit(main())
