"""afmctl: model-based inverse filtering of ferroelectric hysteresis for piezo stages.

Numerics (``hysteresis``, ``rod``, ``transducer``, ``inverse``, ``identify``) are pure; device I/O
lives in the top-level ``drivers`` package, which this package never imports at import time.
"""

__version__ = "0.1.0"
