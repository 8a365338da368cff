"""The ring-light protocol and backend through real pyserial I/O against the simulated controller:
frame round trips, checksums, timeouts and retries, the watchdog, wrong firmware, garbage, lost
connections, and the light model of a sweep."""

from __future__ import annotations

import errno
import time
from pathlib import Path

import numpy as np
import pytest
import serial
from hypothesis import given
from hypothesis import strategies as st

import pstoolkit_ringlight
from pstoolkit.errors import UserError
from pstoolkit.hardware.backend import Sweep
from pstoolkit.optics.lights import RingLight as RingModel
from pstoolkit.optics.lights import build_light_model
from pstoolkit.plugin.options import defaults
from pstoolkit.plugin.registry import Registry
from pstoolkit_ringlight.backend import RingLightBackend, ring_light_spec
from pstoolkit_ringlight.client import (
    DeviceError,
    RingLightClient,
    _open_error,
    port_url,
)
from pstoolkit_ringlight.device import SimulatedRingLight
from pstoolkit_ringlight.protocol import (
    ProtocolError,
    crc8,
    decode,
    encode,
    parse_reply,
    request,
)
from pstoolkit_ringlight.protocol_ringlightsim import device
from pstoolkit_ringlight.ptysim import PtyRingLight

FAST = 0.05  # reply deadline of the tests' tries, seconds


def sim(tmp_path: Path, query: str = "") -> str:
    """A port on a fresh simulated device, named after the test's folder."""
    return f"ringlightsim://{tmp_path.name}" + (f"?{query}" if query else "")


def client(port: str, **kwargs: object) -> RingLightClient:
    c = RingLightClient(port, timeout_s=FAST, **kwargs)  # type: ignore[arg-type]
    c.connect()
    return c


def test_crc8_is_smbus_and_frames_round_trip() -> None:
    assert crc8(b"123456789") == 0xF4 and crc8(b"") == 0
    assert request(0x2A, "CFG", 33333, -1, 1, 2, 3) == b"#2A CFG 33333 -1 1 2 3*" + f"{crc8(b'2A CFG 33333 -1 1 2 3'):02X}".encode() + b"\n"
    assert parse_reply(encode("!", ["07", "OK", "IDLE", "3"])).fields == ("IDLE", "3")
    assert parse_reply(encode("!", ["07", "ER", "4"])).error == "argument out of range"


@given(st.lists(st.text(alphabet="ABCXYZ0123456789-+.", min_size=1, max_size=6), min_size=1, max_size=6))
def test_any_words_round_trip(words: list[str]) -> None:
    assert decode(encode("#", words), "#") == words


def test_damaged_frames_are_rejected() -> None:
    good = encode("!", ["01", "OK"])
    with pytest.raises(ProtocolError, match="bad checksum"):
        decode(good.replace(b"OK", b"OJ"), "!")
    with pytest.raises(ProtocolError, match="not a frame"):
        decode(b"hello\n", "!")
    with pytest.raises(ProtocolError, match="not a frame"):
        decode(good, "#")


def test_commands_round_trip_through_pyserial(tmp_path: Path) -> None:
    c = client(sim(tmp_path, "leds=24"))
    assert (c.info.firmware, c.info.leds, c.info.protocol) == ("pstoolkit-ringlight", 24, 1)
    assert c.request("STAT") == ["IDLE", "0", "1000", "NONE"]
    c.request("CFG", 5000, 1, 1, 1, 1)
    c.request("GO", 0)
    time.sleep(0.012)
    state, turns, _, _ = c.request("STAT")
    assert state == "SWEEP" and int(turns) >= 2
    assert device(tmp_path.name).lit()
    c.request("STOP")
    assert not device(tmp_path.name).lit()
    c.request("LED", 23, 255, 128, 0)
    assert device(tmp_path.name).single == (23, 255, 128, 0)
    with pytest.raises(DeviceError, match=r"^ring light on ringlightsim://.*: LED 24 255 0 0 refused: argument out of range \(code 4\)$"):
        c.request("LED", 24, 255, 0, 0)
    with pytest.raises(DeviceError, match=r": GO 1 refused: not allowed in the current state \(code 5\)$"):
        fresh = client(sim(tmp_path.parent / (tmp_path.name + "-b")))
        fresh.request("GO", 1)
    with pytest.raises(DeviceError, match=r": FLY refused: unknown command \(code 3\)$"):
        c.request("FLY")
    c.close()


def test_a_bad_checksum_gets_error_1_and_the_client_resends(tmp_path: Path) -> None:
    port = serial.serial_for_url(sim(tmp_path), timeout=FAST)
    port.write(request(5, "PING").replace(b"PING", b"PONG"))
    assert port.read_until(b"\n") == encode("!", ["--", "ER", "1"])
    port.close()
    c = client(sim(tmp_path.parent / (tmp_path.name + "-c"), "corrupt=2,3"))
    c.request("CFG", 5000, 1, 1, 1, 1)  # replies 2 and 3 corrupted, the third try gets through
    dev = device(tmp_path.name + "-c")
    assert dev.requests == 4 and dev.config == (5000, 1, 1, 1, 1)


def test_a_lost_reply_times_out_and_is_retried_without_acting_twice(tmp_path: Path) -> None:
    c = client(sim(tmp_path, "drop=2"))
    start = time.perf_counter()
    c.request("CFG", 5000, 1, 1, 1, 1)
    assert time.perf_counter() - start >= FAST
    c.request("GO", 0)
    dev = device(tmp_path.name)
    assert dev.requests == 4 and dev.state == "SWEEP"
    c.request("OFF")


def test_silence_through_every_retry_is_one_error(tmp_path: Path) -> None:
    c = client(sim(tmp_path, "drop=2,3,4"), retries=2)
    with pytest.raises(DeviceError, match=r"^ring light on ringlightsim://\S+: no reply to PING within 50 ms after 3 tries$"):
        c.request("PING")


def test_the_watchdog_turns_the_lights_off_after_silence(tmp_path: Path) -> None:
    c = client(sim(tmp_path))
    c.request("WDG", 200)
    c.request("LED", 0, 255, 255, 255)
    time.sleep(0.08)
    c.request("PING")  # keeps it alive
    time.sleep(0.08)
    assert device(tmp_path.name).lit()
    time.sleep(0.25)
    assert not device(tmp_path.name).lit()
    assert c.request("STAT") == ["IDLE", "0", "200", "WDOG"]
    with pytest.raises(DeviceError, match=r": WDG 50 refused: argument out of range"):
        c.request("WDG", 50)


@pytest.mark.parametrize(
    ("query", "found"),
    [("firmware=marlin&version=2.1", "marlin 2.1 (protocol 1)"), ("protocol=2", "pstoolkit-ringlight 1.0.0 (protocol 2)")],
)
def test_wrong_firmware_is_refused(tmp_path: Path, query: str, found: str) -> None:
    with pytest.raises(DeviceError) as info:
        client(sim(tmp_path, query))
    assert str(info.value) == (
        f"ring light on {sim(tmp_path, query)}: wrong firmware {found}; "
        "expected pstoolkit-ringlight with protocol 1 (flash examples/firmware/ringlight)"
    )


def test_a_device_that_answers_garbage(tmp_path: Path) -> None:
    with pytest.raises(DeviceError, match=r"^ring light on \S+: answers garbage, not the ring-light protocol \(last reply b'\\x00\\xfe\?\? ringlight"):
        client(sim(tmp_path, "garbage=1"), retries=1)


def test_port_errors_are_one_line(tmp_path: Path) -> None:
    missing = str(tmp_path / "ttyACM9")
    with pytest.raises(DeviceError, match=rf"^ring light port {missing}: no such device \(is it plugged in\?"):
        client(missing)
    denied = _open_error("/dev/ttyUSB0", serial.SerialException(errno.EACCES, "could not open port /dev/ttyUSB0: [Errno 13] Permission denied"))
    assert str(denied) == "ring light port /dev/ttyUSB0: permission denied (on Linux add yourself to the 'dialout' group)"
    assert port_url("sim") == "ringlightsim://sim" and port_url("/dev/ttyACM0") == "/dev/ttyACM0"


def test_a_blip_reconnects_but_an_unplugged_device_is_an_error(tmp_path: Path) -> None:
    c = client(sim(tmp_path, "blip=2"))
    assert c.request("PING") == []  # broke after the device acted; reopened; the resend is answered from its cache
    assert device(tmp_path.name).requests == 3
    gone = client(sim(tmp_path.parent / (tmp_path.name + "-d"), "disconnect=2"))
    with pytest.raises(DeviceError, match=r"^ring light on \S+: connection lost during PING and the port cannot be reopened \(could not open port"):
        gone.request("PING")


def test_the_backend_leaves_the_lights_off_on_errors(tmp_path: Path) -> None:
    options = {**defaults(RingLightBackend.options), "timeout_ms": 50}
    with pytest.raises(RuntimeError):
        with RingLightBackend(sim(tmp_path), options) as rig:
            rig.configure(Sweep(6000))
            rig.start()
            assert device(tmp_path.name).lit()
            raise RuntimeError("camera failed")
    assert not device(tmp_path.name).lit()
    with pytest.raises(UserError, match=r"a period of 100 µs is too short for 60 LEDs$"):
        with RingLightBackend(sim(tmp_path.parent / (tmp_path.name + "-e")), options) as rig:
            rig.configure(Sweep(100))


def test_led_gains_are_loaded(tmp_path: Path) -> None:
    gains = tmp_path / "gains.txt"
    gains.write_text("\n".join(f"{i} 255 {255 - i}" for i in range(4)))
    options = {**defaults(RingLightBackend.options), "gains": str(gains)}
    with RingLightBackend(sim(tmp_path, "leds=4"), options):
        assert device(tmp_path.name).gains == [(0, 255, 255), (1, 255, 254), (2, 255, 253), (3, 255, 252)]
    gains.write_text("1 2 3\n")
    with pytest.raises(UserError, match=r"gains\.txt: expected 4 lines of 'r g b' gains for 4 LEDs, got shape \(1, 3\)$"):
        with RingLightBackend(sim(tmp_path, "leds=4"), options):
            pass


def test_the_sweep_light_model_follows_the_ring() -> None:
    ring = RingModel(elevation_deg=40.0, period_us=36000, phase_deg=30.0, sense=-1, t0_us=500)
    for smooth in (True, False):
        spec = ring_light_spec(36, Sweep(36000, sense=-1, smooth=smooth), 500, 40.0, 30.0)
        model = build_light_model(spec)
        peaks = 500 + np.arange(36) * 1000.0
        got, intensity = model.evaluate(peaks + 72000)  # two turns later: periodic
        want, _ = ring.evaluate(peaks)
        assert np.abs(got - want).max() < 1e-9 and np.all(intensity == 1.0)
    # halfway between two LEDs both shine at half strength: the light is their normalised mean
    smooth_model = build_light_model(ring_light_spec(36, Sweep(36000, sense=-1), 500, 40.0, 30.0))
    between, _ = smooth_model.evaluate(np.array([1000.0]))
    leds, _ = ring.evaluate(np.array([500.0, 1500.0]))
    blend = leds.sum(axis=0) / np.linalg.norm(leds.sum(axis=0))
    assert np.abs(between[0] - blend).max() < 1e-12


def test_the_plugin_registers_the_backend() -> None:
    registry = Registry("backend")
    pstoolkit_ringlight.pstoolkit_register_backends(registry)
    assert registry.names() == ["ringlight"] and registry.get("ringlight").obj is RingLightBackend


def test_the_simulated_device_on_a_pty_pair_through_the_os_serial_layer(tmp_path: Path) -> None:
    with PtyRingLight(SimulatedRingLight(leds=12)) as server:
        c = client(server.path)
        assert (c.info.leds, type(c._serial).__module__) == (12, "serial.serialposix")
        c.request("WDG", 100)
        c.request("LED", 3, 255, 255, 255)
        assert server.device.lit()
        time.sleep(0.15)
        assert c.request("STAT") == ["IDLE", "0", "100", "WDOG"]
        c.close()
