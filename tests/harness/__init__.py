"""Test harnesses shared by the tests and the benchmarks (``tests.harness.*``).

:mod:`~tests.harness.campaign` is the safety campaign (random waveforms, wire faults, watchdog
trials); :mod:`~tests.harness.independent_stage` a stage device written from ``docs/protocol.md``
apart from afmctl's emulator; :mod:`~tests.harness.paths` the checkout's folders.
"""
