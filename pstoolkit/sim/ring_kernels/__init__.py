"""The compiled kernels of the simulator's ring-light engine (``pstoolkit.sim.ring_engine`` is their
Python driver), one module a job:

- ``tuning``: the engine's work sizes and step limits;
- ``inputs``: what the kernels read, built once per capture — the closed form's per-pixel constants,
  the event pixels' footprints, the ring light's parameters — and the per-pixel state they update;
- ``lanes``: a thread's ``LANES`` pixels stepped at once — their shading, log and turn of the light;
- ``firing``: the event rule on the lanes' lines, both refractory rules, and the events' times;
- ``shadow_table``: which frame pixels a cast shadow falls on while lit, per block of time;
- ``stepper``: the per-pixel adaptive time steps over a block, in parallel over event pixels;
- ``output``: a block's events sorted by time and a window's exposure images.

The kernels take their many arrays grouped in ``NamedTuple`` records (``inputs``), which numba passes
as plain structs.
"""
