"""The pipeline: the stages run in order over an AOI (or its tiles), and the run's outputs.

``reconstruct`` (``run``) is the whole job of ``satsweep reconstruct``.
"""
