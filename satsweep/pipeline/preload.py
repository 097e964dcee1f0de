"""Libraries that later stages import, imported in a background thread while the first stages
run (a fresh process spends most of a second importing them).
"""

from __future__ import annotations

import importlib
import threading

# Libraries the later stages import (OpenCV: SIFT, the tie points' registration, the coarse
# pass's and the DSM's filters): a background thread imports them while the main thread opens
# the device and reads the images. (reconstruct no longer imports SciPy, whose modules took a
# fresh process about 0.7 s to import.)
PRELOADED_MODULES = ("cv2",)


def start_preloading() -> threading.Thread:
    """Import PRELOADED_MODULES in a daemon thread; returns the thread (started)."""

    def run():
        for name in PRELOADED_MODULES:
            try:
                importlib.import_module(name)
            except ImportError:  # the stage that needs it imports it again and reports it
                return

    thread = threading.Thread(target=run, name="satsweep-preload", daemon=True)
    thread.start()
    return thread
