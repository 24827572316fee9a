"""File formats: one module per kind of file a lab keeps or edits.

What belongs here: sweep files (:mod:`~afmctl.files.sweepfile`, CSV with ``#`` metadata and the
spellings labs use), stage profiles (:mod:`~afmctl.files.profile`), model files
(:mod:`~afmctl.files.modelfile`), run files (:mod:`~afmctl.files.runfile`), waveform files
(:mod:`~afmctl.files.waveformfile`) and the TOML reader and writer they share
(:mod:`~afmctl.files.tomlfile`). Reading and writing only: no numerics beyond checking what is read.
"""
