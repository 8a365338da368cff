"""The integers the toolkit accepts from a file or the command line."""

INT_RANGE = (-(1 << 63), (1 << 63) - 1)
"""Integers accepted: int64's (what torch, numpy and numba take; a solver's seed too)."""
