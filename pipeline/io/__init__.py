"""Readers and writers, one per file schema of DESIGN.md (each round-trip tested)."""
