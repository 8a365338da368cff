"""The ring-light engine's step limits and work sizes. The work sizes only change speed and memory,
never the events; how each was chosen is measured in ``docs/simulator-tuning.md``."""

from __future__ import annotations

# Longest step, as a share of the light's turn, away from the shadow-grid intervals in which a cast shadow falls on
# the pixel while it is lit (around those a pixel steps at most one interval, so no sweep is stepped over).
MAX_STEP_TURNS = 8.0 / 360.0
# Largest distance of L from the line of a pixel's previous step at the end of the next one: the line
# between the step's samples is then within about a quarter of it (1e-3) of L, so events keep the
# threshold rule where L curves (a highlight) even when its change over the step is small.
MAX_BEND = 4e-3
# Event pixels handed to a thread at a time: pixels differ a lot in work (a dark background pixel
# against one a shadow edge sweeps), so threads take chunks as they finish instead of equal shares;
# a chunk is long enough that its lanes are seldom idle (a task's last pixels leave lanes without work).
PIXELS_PER_TASK = 1024
# Pixels a task steps at once (see ``pstoolkit.sim.ring_kernels.stepper``): their state across the
# lanes makes the shading, log, step control and firing rule SIMD loops.
LANES = 32
# Length of a block of time, in shadow-grid intervals: one shadow table and one batch of events. Each
# block ends with a sample of every pixel and costs a table, masks and an event sort.
BLOCK_GRID_STEPS = 60
# Most grid times in a block's shadow table: one bit each in ``lit_shadow``'s masks. A block of n
# intervals that starts between grid times spans up to n + 3 of them, so a block is at most
# ``TABLE_ROWS`` − 3 intervals long (a window's short last stretch joins the block before only within it).
TABLE_ROWS = 64
# Columns of the shadow table whose masks ``lit_shadow`` builds at once: their 8 KiB of bits stay in
# the L1 cache while the table's rows stream by.
SHADOW_TILE = 1024
# First room for events per pixel and block, and the most memory (bytes) it may take at first: a pixel
# that fires more is run again from its state at the block's start, and the room widens to the
# busiest pixel's count.
FIRST_ROOM = 128
ROOM_BYTES = 32 << 20
# Runs of pixels the event sort of a block counts and places in parallel (see ``output.gather``); fixed, so
# the work does not depend on the threads.
GATHER_RUNS = 16
