"""The byte layout of one ECF chunk (Prophesee's HDF5 filter 0x8ECF), as this decoder reads it.

A chunk of ``n`` CD events is, in order (all integers little-endian):

- a u32 header: ``n << 2 | mode``; bit 1 set: *packed* (y, x, p in 24 bits per event); else bit 0
  set: *rle_y + packed_xp*; neither: *rle_y + masked_x + rle_p*;
- the times: an i64 origin, then one group per distinct time: escape bytes ``0xF_`` each holding a
  4-bit digit of the delta (least significant first, at most 16), then a byte ``d << 4 | c``: ``d``
  the next digit, ``c`` the number of events at that time (``c`` = 15: a u16 count follows). Each
  delta is added to the previous time (the origin for the first group);
- packed: ``ceil(n / 4)`` groups of three u32 words holding four 24-bit values ``y << 12 | x << 1 | p``
  (a: w0 >> 8; b: w0 & 0xFF | (w1 >> 16) << 8; c: w1 & 0xFFFF | (w2 >> 24) << 16; d: w2 & 0xFFFFFF);
- otherwise the rows: u16 words ``y << 5 | c`` (``c`` = 31: a u16 count follows) giving the row of
  the next ``c`` events; then, for rle_y + packed_xp, ``ceil(n / 4)`` groups of three u16 words
  holding four 12-bit values ``x << 1 | p`` laid out as above at half the width; for
  rle_y + masked_x + rle_p, u16 words ``x << 5 | mask`` giving the event at x and one at ``x + 1 + k``
  for each set mask bit ``4 - k`` (events in that order, bits past ``n`` ignored), then polarity runs
  as bytes ``p << 7 | c`` (``c`` = 127: a u16 count follows).

Slots past ``n`` in a last group and mask bits past ``n`` may hold anything (a reused encoder leaves
its previous chunk there) and are ignored. x and y are 11-bit, so at most 2047.
"""

from __future__ import annotations

FILTER_ID = 0x8ECF
MAX_CHUNK_EVENTS = 65535
"""The codec's largest chunk; a header counting more is refused before anything is allocated."""
HEADER_BYTES, ORIGIN_BYTES = 4, 8
MODE_PACKED, MODE_PACKED_XP = 2, 1
MAX_DIGITS = 16

OK, SHORT, OVERRUN, LONG_DELTA, TIME_BACK, OUTSIDE = 0, 1, 2, 3, 4, 5
MESSAGES = {
    SHORT: "ends before the events its header counts",
    OVERRUN: "holds a run of more events than its header counts",
    LONG_DELTA: "holds a time step of more than 64 bits",
    TIME_BACK: "has a time going back",
    OUTSIDE: "has events outside the sensor geometry",
}
"""What each status code of the kernels says about a chunk."""
