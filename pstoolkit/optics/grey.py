"""The grey of a linear RGB value, as an event sensor sees it."""

GREY_WEIGHTS = (0.299, 0.587, 0.114)
"""Rec. 601 luma: the grey an event sensor (and a grey solve) sees of linear RGB."""
