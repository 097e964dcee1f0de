"""Synthetic scenes with exact truth (``satsweep synth``): a seeded town, pushbroom satellites that
see it, images rendered by ray casting, RPCs fitted to the cameras, and the truth DSM.

- ``scene``: ``generate_scene`` and its options; ``town``: the surface, rays and shadows;
  ``pushbroom``: the satellite cameras; ``rpcfit``: RPCs fitted to them; ``multidate``: scenes
  taken on several dates (sun, seasons, transients, radiometry, acquisition metadata).
"""
