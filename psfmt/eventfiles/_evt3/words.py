"""The EVT 3.0 word layout: 16-bit little-endian words with the type in bits 15..12."""

from __future__ import annotations

ADDR_Y, ADDR_X, VECT_BASE_X, VECT_12, VECT_8, TIME_LOW, TIME_HIGH, EXT_TRIGGER = 0x0, 0x2, 0x3, 0x4, 0x5, 0x6, 0x8, 0xA
SKIPPED_TYPES = (0x7, 0xE, 0xF)  # CONTINUED_4, OTHERS, CONTINUED_12: defined, carry no CD event
WRAP_US = 1 << 24
WRAP_DROP = 2048  # a TIME_HIGH this far below the previous one is a wrap, a smaller drop a step back
VECTOR_MIN_EVENTS = 5  # a base and a triplet cost 4 words: vectors pay from 5 events on
MAX_COORD = 2047
