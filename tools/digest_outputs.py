#!/usr/bin/env python3
"""SHA-256 of the products of reconstructions (DSM, confidence, orthophoto, cloud), to show that a
change leaves results bit for bit the same: run it on the output folders before and after, then
compare the two JSON files (``--compare``). A GeoTIFF's digest is that of its decoded pixels
(shape, type and values of its first page), so that a change of file layout or compression
alone leaves it the same; a cloud's is that of its bytes.

    python tools/digest_outputs.py /tmp/before -o before.json   # every run folder under it
    python tools/digest_outputs.py /tmp/after -o after.json --compare before.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

PRODUCTS = ("dsm.tif", "confidence.tif", "ortho.tif", "count.tif", "cloud.ply")


def _digest(path: Path) -> str:
    if path.suffix != ".tif":
        return hashlib.sha256(path.read_bytes()).hexdigest()
    import numpy as np
    import tifffile

    pixels = np.ascontiguousarray(tifffile.imread(path, key=0))
    h = hashlib.sha256(f"{pixels.shape} {pixels.dtype.str}".encode())
    h.update(pixels.tobytes())
    return h.hexdigest()


def digests(root: Path) -> dict[str, str]:
    out = {}
    for name in PRODUCTS:
        for path in sorted(root.rglob(name)):
            out[str(path.relative_to(root))] = _digest(path)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("root", type=Path, help="folder holding reconstructions (searched recursively)")
    p.add_argument("-o", "--output", type=Path, default=None, help="write the digests here (JSON)")
    p.add_argument("--compare", type=Path, default=None, help="digests of an earlier run (JSON)")
    args = p.parse_args(argv)
    found = digests(args.root)
    if args.output:
        args.output.write_text(json.dumps(found, indent=1) + "\n")
    if args.compare is None:
        print(json.dumps(found, indent=1))
        return 0
    before = json.loads(args.compare.read_text())
    differ = sorted(k for k in set(before) | set(found) if before.get(k) != found.get(k))
    for k in differ:
        print(f"DIFFERS: {k}")
    print(f"{len(set(before) & set(found)) - len([k for k in differ if k in before and k in found])}"
          f" of {len(set(before) | set(found))} products identical")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
