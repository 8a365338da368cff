"""The simulated ring light on a pseudo-terminal pair: a real serial device path for any program.

``python -m pstoolkit_ringlight.ptysim [--leds N]`` prints a path such as ``/dev/pts/7`` and serves
until Ctrl-C; ``pstoolkit capture --port /dev/pts/7 …`` then talks to it through the operating
system's serial layer exactly as to a USB controller. POSIX only.
"""

from __future__ import annotations

import argparse
import os
import select
import threading
import tty

from pstoolkit_ringlight.device import SimulatedRingLight
from pstoolkit_ringlight.protocol import MAX_LINE


class PtyRingLight:
    """Serves ``device`` on the controller end of a pty pair; ``path`` is the end to open."""

    def __init__(self, device: SimulatedRingLight) -> None:
        self.device = device
        self._controller, self._port = os.openpty()
        tty.setraw(self._port)  # no echo and no line editing, like a USB serial device
        self.path = os.ttyname(self._port)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="ringlight-pty", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        pending = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self._controller], [], [], 0.02)
            if not ready:
                continue
            try:
                pending += os.read(self._controller, 256)
            except OSError:  # the last opener closed its end; wait for the next one
                continue
            while b"\n" in pending:
                line, _, pending = pending.partition(b"\n")
                reply = self.device.receive(line.rstrip(b"\r"))
                if reply:
                    os.write(self._controller, reply)
            if len(pending) > 4 * MAX_LINE:  # noise without newlines: the firmware drops it too
                pending = b""

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        os.close(self._controller)
        os.close(self._port)

    def __enter__(self) -> PtyRingLight:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main() -> None:
    parser = argparse.ArgumentParser(description="Serve a simulated ring light on a pty pair.")
    parser.add_argument("--leds", type=int, default=60, help="number of LEDs of the ring")
    args = parser.parse_args()
    with PtyRingLight(SimulatedRingLight(leds=args.leds)) as server:
        print(server.path, flush=True)
        try:
            threading.Event().wait()
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":
    main()
