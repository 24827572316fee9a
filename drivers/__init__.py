"""Device I/O for afmctl (placeholder; see issue 3)."""
