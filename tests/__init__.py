"""afmctl's tests: one folder per room of the package, ``system/`` for the cross-process ones."""
