"""Shipped stage profiles (package data, so ``default_profile()`` works from an installed wheel)."""
