"""The paper's data accounting: bytes per light period against 24 8-bit RGB frames.

Frames count one byte per pixel and channel (the 24-bit RGB of a frame camera, whatever the stored
depth), events two bytes each (one 16-bit EVT 3.0 word per event, the paper's estimate), and 100 %
is 24 RGB frames of the target resolution. A capture spanning several periods of a periodic light
is divided by the number of periods, so the rate describes one sweep as in the paper's tables.
"""

from __future__ import annotations

from dataclasses import dataclass

from psfmt.model import Capture

REFERENCE_FRAMES = 24
EVENT_WORD_BYTES = 2


@dataclass
class DataRate:
    frame_bytes: float
    event_bytes: float
    reference_bytes: float
    periods: float

    @property
    def rate(self) -> float:
        """Fraction of the reference (0.181 for the paper's 18.1 %)."""
        return (self.frame_bytes + self.event_bytes) / self.reference_bytes

    @property
    def frame_rate(self) -> float:
        return self.frame_bytes / self.reference_bytes

    @property
    def event_rate(self) -> float:
        return self.event_bytes / self.reference_bytes


def target_size(capture: Capture) -> tuple[int, int]:
    """(H, W) of the normal map a solver targets: the frames, else the ground truth, else the event sensor."""
    if capture.frames is not None:
        return capture.frames.height, capture.frames.width
    gt = capture.ground_truth
    if gt is not None and gt.normal is not None:
        return int(gt.normal.shape[0]), int(gt.normal.shape[1])
    if capture.events is not None:
        return capture.events.height, capture.events.width
    return 0, 0


def time_span_us(capture: Capture) -> tuple[int, int] | None:
    """First and last instant the capture covers (exposure windows and events), if timed at all."""
    starts, ends = [], []
    frames = capture.frames
    if frames is not None and frames.has_windows:
        starts.append(int(frames.t_start_us.min()))
        ends.append(int(frames.t_end_us.max()))
    events = capture.events
    if events is not None and len(events):
        starts.append(int(events.t_first_us))
        ends.append(int(events.t_last_us) + 1)
    return (min(starts), max(ends)) if starts else None


def light_periods(capture: Capture) -> float:
    """Whole light periods the capture spans (1 when the light is not periodic or not timed)."""
    lights, span = capture.lights, time_span_us(capture)
    if lights is None or span is None:
        return 1.0
    period = lights.params.get("period_us")
    periodic = lights.params.get("periodic", lights.model != "sampled")
    if not period or not periodic:
        return 1.0
    return float(max(1, round((span[1] - span[0]) / float(period))))


def data_rate(
    capture: Capture,
    *,
    frames: int | None = None,
    events: bool = True,
    event_bytes: float | None = None,
) -> DataRate:
    """Data per period relative to 24 RGB frames.

    By default everything the capture holds counts; a solver that used only some of it is accounted
    with ``frames`` (how many of the capture's frames it read; 0 for none) and ``events=False``.
    ``event_bytes`` overrides the 2-bytes-per-event estimate (e.g. a real EVT 3.0 encoding)."""
    h, w = target_size(capture)
    periods = light_periods(capture)
    stack = capture.frames
    count = 0 if stack is None else stack.count if frames is None else min(int(frames), stack.count)
    frame_bytes = count * stack.height * stack.width * stack.channels if stack is not None else 0
    if not events or capture.events is None:
        event_bytes = 0.0
    elif event_bytes is None:
        event_bytes = EVENT_WORD_BYTES * len(capture.events)
    return DataRate(
        frame_bytes=frame_bytes / periods,
        event_bytes=event_bytes / periods,
        reference_bytes=float(REFERENCE_FRAMES * h * w * 3) or 1.0,
        periods=periods,
    )
