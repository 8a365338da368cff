"""Issue 25: RAW headers as they come off the camera: geometry resolved the way Metavision does, lines
in any order, the header corpus of ``tests/fuzz/corpus/raw_headers`` and fuzzed variants of it."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from helpers.prophesee import GEN3_EVT2, GEN41_EVT3
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from psfmt.errors import FormatError
from psfmt.eventfiles import evt2, evt3
from psfmt.eventfiles.rawheader import missing_geometry, read_header, resolve_geometry
from psfmt.eventfiles.rawsensors import PLUGINS, SENSOR_GENERATIONS, SENSOR_NAMES, SYSTEM_IDS, implied_sensor, integrator
from psfmt.events import EventArray
from psfmt.text import printable

CORPUS = Path(__file__).resolve().parents[1] / "fuzz" / "corpus" / "raw_headers"
EXPECTED = json.loads((CORPUS / "expected.json").read_text())



def stream(width: int, height: int, n: int = 4000, seed: int = 0) -> EventArray:
    """Sorted events that reach the last column and row of the sensor."""
    rng = np.random.default_rng(seed)
    x, y = rng.integers(0, width, n), rng.integers(0, height, n)
    x[n // 2], y[n // 3] = width - 1, height - 1
    return EventArray(x, y, np.sort(rng.integers(0, 3 << 24, n)), rng.choice([-1, 1], n))


def body(encoding: str, events: EventArray) -> bytes:
    return evt3.encode(events) if encoding == "EVT3" else evt2.encode(events)[0]


def same(a: EventArray, b: EventArray) -> bool:
    return len(a) == len(b) and all(np.array_equal(getattr(a, c), getattr(b, c)) for c in "xytp")


@pytest.mark.parametrize(
    "text,encoding,geometry,source,reader",
    [
        (GEN41_EVT3, "EVT3", (1280, 720), "system_ID 48 (Gen4.1)", evt3.Evt3File),
        (GEN3_EVT2, "EVT2", (640, 480), "system_ID 21 (Gen3.0)", evt2.Evt2File),
    ],
)
def test_the_two_headers_of_the_issue_open_as_they_are(
    tmp_path: Path, text: str, encoding: str, geometry: tuple[int, int], source: str, reader: type
) -> None:
    events = stream(*geometry)
    path = tmp_path / "rec.raw"
    path.write_bytes(text.encode("ascii") + body(encoding, events))
    header = read_header(path)
    assert (header.width, header.height, header.encoding, header.geometry_source) == (*geometry, encoding, source)
    assert header.lines == text.splitlines()
    rec = reader(path)
    decoded = rec.read()[0]
    assert (rec.width, rec.height) == geometry and rec.stats.clean
    assert same(decoded, events) and int(decoded.x.max()) == geometry[0] - 1 and int(decoded.y.max()) == geometry[1] - 1


@pytest.mark.parametrize("order", list(itertools.islice(itertools.permutations(range(7)), 0, None, 97)))
def test_the_evt_line_and_the_others_may_come_in_any_order(tmp_path: Path, order: tuple[int, ...]) -> None:
    lines = GEN41_EVT3.splitlines()
    path = tmp_path / "shuffled.raw"
    events = stream(1280, 720, 300)
    path.write_bytes("".join(lines[k] + "\n" for k in order).encode() + evt3.encode(events))
    header = read_header(path)
    assert (header.width, header.height, header.encoding) == (1280, 720, "EVT3")
    assert sorted(header.lines) == sorted(lines)
    assert same(evt3.Evt3File(path).read()[0], events)


def resolved(fields: dict[str, str], override: tuple[int, int] | None = None) -> tuple[int, int, str] | None:
    return resolve_geometry(fields, Path("h.raw"), "RAW", override)


def test_the_order_of_the_sources() -> None:
    implied = {"system_ID": "21", "plugin_name": "hal_plugin_gen41_evk3", "sensor_name": "GenX320", "sensor_generation": "4.0"}
    declared = {"geometry": "100x50", "format": "EVT3;height=50;width=100", "Width": "7", "Height": "9"}
    fields = {**declared, **implied}
    assert resolved(fields) == (100, 50, "geometry 100x50")
    assert resolved(fields, (33, 44)) == (33, 44, "--geometry 33x44")
    del fields["geometry"]
    assert resolved(fields) == (100, 50, "format EVT3;height=50;width=100")
    del fields["format"]
    assert resolved(fields) == (7, 9, "Width 7, Height 9")
    del fields["Width"]
    assert resolved(fields) == (640, 480, "system_ID 21 (Gen3.0)")
    del fields["system_ID"]
    assert resolved(fields) == (1280, 720, "plugin_name hal_plugin_gen41_evk3 (Gen4.1)")
    del fields["plugin_name"]
    assert resolved(fields) == (320, 320, "sensor_name GenX320")
    del fields["sensor_name"]
    assert resolved(fields) == (1280, 720, "sensor_generation 4.0 (Gen4.0)")
    del fields["sensor_generation"]
    assert resolved(fields) is None
    # the override wins even over a declared geometry that could not be read
    assert resolved({"geometry": "wide"}, (64, 48)) == (64, 48, "--geometry 64x48")
    with pytest.raises(FormatError, match=r"each side must be 1…65536 pixels"):
        resolved({}, (0, 48))
    # header text in a message is shown printable and bounded
    with pytest.raises(FormatError) as err:
        resolved({"geometry": "\x1b[2J" + "9" * 300})
    assert str(err.value) == printable(str(err.value)) and len(str(err.value)) < 200 and str(err.value).endswith("…)")


def test_the_sensor_tables_are_prophesee_s_and_apply_only_to_its_files() -> None:
    assert integrator({}) == "Prophesee"  # Metavision takes a file naming no integrator for Prophesee's
    assert integrator({"integrator_name": "Acme"}) == "Acme"
    assert integrator({"camera_integrator_name": "Prophesee", "plugin_integrator_name": "Prophesee", "integrator_name": "Acme"}) == "Prophesee"
    assert integrator({"camera_integrator_name": "Acme", "plugin_integrator_name": "Prophesee"}) == "Prophesee/Acme"
    assert implied_sensor({"system_ID": "48", "integrator_name": "Acme"}) is None
    assert implied_sensor({"system_ID": "48abc"})[1] == "system_ID 48abc (Gen4.1)"  # read as std::stol does
    # each table's geometry is its sensor's
    for sensor, _ in SYSTEM_IDS.values():
        assert SENSOR_NAMES[sensor.name] == sensor
    assert {s.name for s in PLUGINS.values()} <= set(SENSOR_NAMES) and {s.name for s in SENSOR_GENERATIONS.values()} <= set(SENSOR_NAMES)
    sizes = {name: (s.width, s.height) for name, s in SENSOR_NAMES.items()}
    assert sizes == {
        "Gen3.0": (640, 480), "Gen3.1": (640, 480), "Gen4.0": (1280, 720), "Gen4.1": (1280, 720),
        "IMX636": (1280, 720), "IMX646": (1280, 720), "GenX320": (320, 320),
    }
    assert "4.2" not in SENSOR_GENERATIONS  # IMX636/IMX646 (HD) and IMX637/IMX647 (VGA) all report 4.2


def test_a_header_without_geometry_is_one_line_listing_what_was_looked_for(tmp_path: Path) -> None:
    path = tmp_path / "anonymous.raw"
    path.write_bytes(b"% evt 3.0\n% plugin_name hal_plugin_mystery\n% system_ID 99\n" + evt3.encode(stream(16, 16, 20)))
    header = read_header(path)
    assert header.width is None and header.encoding == "EVT3"
    message = missing_geometry(header)
    assert "\n" not in message
    assert message == (
        "RAW header declares no sensor geometry: no % geometry WxH, no width=/height= in % format, no % Width/% Height, "
        "and no Prophesee sensor known from system_ID, plugin_name, sensor_name or sensor_generation "
        "(system_ID 99, plugin_name hal_plugin_mystery: not in the sensor tables)"
    )
    with pytest.raises(FormatError) as err:
        evt3.Evt3File(path)
    assert str(err.value) == f"{path}: {message}"
    assert len(evt3.Evt3File(path, geometry=(16, 16)).read()[0]) == 20
    assert evt3.Evt3File(path, geometry=(16, 16)).header.geometry_source == "--geometry 16x16"


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_the_header_corpus(tmp_path: Path, name: str) -> None:
    expected = EXPECTED[name]
    text = (CORPUS / name).read_bytes()
    path = tmp_path / "case.raw"
    if "error" in expected:
        path.write_bytes(text + bytes(range(256)))
        try:
            header = read_header(path)
        except FormatError as exc:
            assert expected["error"] in str(exc) and "\n" not in str(exc)
        else:
            assert header.width is None and expected["error"] in missing_geometry(header)
        return
    width, height = expected["geometry"]
    encoding = expected["encoding"]
    events = stream(width, height, 500)
    path.write_bytes(text + (body(encoding, events) if encoding in ("EVT3", "EVT2") else b""))
    header = read_header(path)
    assert (header.width, header.height, header.geometry_source, header.encoding) == (width, height, expected["source"], encoding)
    assert len(header.lines) == text.count(b"\n") - text.count(b"% end\n")
    if encoding in ("EVT3", "EVT2"):
        reader = evt3.Evt3File(path) if encoding == "EVT3" else evt2.Evt2File(path)
        assert same(reader.read()[0], events) and reader.stats.clean


CASES = sorted(name for name in EXPECTED if "error" not in EXPECTED[name])


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    name=st.sampled_from(CASES),
    order=st.randoms(use_true_random=False),
    drop=st.lists(st.integers(0, 20), max_size=3),
    garble=st.lists(st.tuples(st.integers(0, 20), st.binary(min_size=1, max_size=12).filter(lambda b: b"\n" not in b)), max_size=2),
)
def test_fuzzed_header_variants_give_a_geometry_or_one_line(tmp_path: Path, name: str, order, drop: list[int], garble: list) -> None:  # type: ignore[no-untyped-def]
    """Corpus headers with lines reordered, dropped or garbled: reading gives a header (with a geometry
    inside 1…65536, or a one-line reason there is none) or one FormatError line, never anything else;
    a variant that keeps every line reads exactly as the original."""
    lines = (CORPUS / name).read_bytes().splitlines(keepends=True)
    order.shuffle(lines)
    lines = [line for k, line in enumerate(lines) if k not in drop]
    for k, junk in garble:
        if lines:
            at = k % len(lines)
            lines[at] = lines[at][:2] + junk + lines[at][2 + len(junk):]
    path = tmp_path / "variant.raw"
    path.write_bytes(b"".join(lines) + np.arange(64, dtype="<u2").tobytes())
    try:
        header = read_header(path)
    except FormatError as exc:
        assert str(exc) == printable(str(exc)) and str(exc).startswith(str(path))  # one line, no terminal controls
        return
    if header.width is None:
        assert missing_geometry(header) == printable(missing_geometry(header))
    else:
        assert 0 < header.width <= 1 << 16 and 0 < header.height <= 1 << 16 and header.geometry_source
    keys = [line.split()[1] for line in lines if len(line.split()) > 1]
    if not drop and not garble and len(keys) == len(set(keys)) and b"% end\n" not in b"".join(lines[:-1]):
        expected = EXPECTED[name]
        assert [header.width, header.height] == expected["geometry"] and header.encoding == expected["encoding"]


def test_the_documented_table_is_the_code_s() -> None:
    """docs/event-files.md's geometry table lists exactly the entries of ``psfmt.eventfiles.rawsensors``."""
    doc = (Path(__file__).resolve().parents[2] / "docs" / "event-files.md").read_text()
    rows = [line.split("|")[1:-1] for line in doc.splitlines() if line.startswith("| ") and "×" in line.split("|")[2]]
    documented: dict[str, set[str]] = {"system_ID": set(), "plugin_name": set(), "sensor_name": set(), "sensor_generation": set()}
    for sensor, size, ids, plugins, names, generations in (cells for cells in rows if len(cells) == 6):
        w, h = (int(v) for v in size.strip().split("×"))
        name = sensor.split("(")[0].strip()
        assert (SENSOR_NAMES[name].width, SENSOR_NAMES[name].height) == (w, h)
        documented["system_ID"] |= {f"{v.strip()}:{name}" for v in ids.split(",") if v.strip() != "—"}
        documented["plugin_name"] |= {f"{v.strip(' `')}:{name}" for v in plugins.split(",") if v.strip() != "—"}
        documented["sensor_name"] |= {f"{v.strip(' `')}:{name}" for v in names.split(",") if v.strip() != "—"}
        documented["sensor_generation"] |= {f"{v.strip(' `')}:{name}" for v in generations.split(",") if v.strip() != "—"}
    assert documented["system_ID"] == {f"{k}:{s.name}" for k, (s, _) in SYSTEM_IDS.items()}
    assert documented["plugin_name"] == {f"{k}:{s.name}" for k, s in PLUGINS.items()}
    assert documented["sensor_name"] == {f"{k}:{s.name}" for k, s in SENSOR_NAMES.items()}
    assert documented["sensor_generation"] == {f"{k}:{s.name}" for k, s in SENSOR_GENERATIONS.items()}
    evt3_ids = sorted(k for k, (_, enc) in SYSTEM_IDS.items() if enc == "EVT3")
    assert f"system_IDs {', '.join(map(str, evt3_ids[:-1]))} and {evt3_ids[-1]} imply EVT 3.0" in doc
