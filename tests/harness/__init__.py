"""Test harnesses shared by the tests and the benchmarks (``tests.harness.*``).

:mod:`~tests.harness.campaign` is the safety campaign (random waveforms, wire faults, watchdog
trials); :mod:`~tests.harness.second_device` a second stage device written from
``docs/reference/protocol.md`` alone (no afmctl code; conforming and deliberately broken variants), and
:mod:`~tests.harness.independent_stage` that device driving a foreign plant;
:mod:`~tests.harness.paths` the checkout's folders.
"""
