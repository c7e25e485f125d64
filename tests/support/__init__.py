"""Test support: the plain-numpy reference bank, harnesses, fixtures."""
