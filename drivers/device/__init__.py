"""The device side: what a stage controller does, apart from the host.

The emulated stage's logic, its plants (afmctl's own model, and an independently written
foreign plant with hidden effects), the wire servers, fault injection, and the conformance check
that exercises any device against ``docs/protocol.md``. Host code (``afmctl`` and the links in
:mod:`drivers`) never imports from here except to start an emulated stage.
"""
