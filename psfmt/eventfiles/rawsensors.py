"""The Prophesee sensors a RAW header implies when it declares no geometry, as Metavision reads them.

Files written by Metavision before it added ``% format …;width=W;height=H`` (and ``% geometry``) name
no sensor size; Metavision then takes it from the camera's ``system_ID`` (``PseeRawFileHeader::
check_header`` in OpenEB's ``hal_psee_plugins``), and OpenEB 2.x from the ``plugin_name`` (the
``plugins_map`` of ``hal_openeb_plugins``). Both tables are Prophesee's own, so both apply only to a
file whose integrator is Prophesee (or that names none, which Metavision takes for Prophesee).
``sensor_name`` and ``sensor_generation``, which Metavision writes beside them, name the sensor too.

Every entry was checked against OpenEB's source (``docs/event-files.md`` lists the files); an entry
that could not be checked is left out: ``sensor_generation 4.2`` is IMX636 and IMX646 (1280×720) but
also IMX637 and IMX647, so it names no single geometry.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from psfmt.text import printable


@dataclass(frozen=True)
class Sensor:
    """A sensor generation: Metavision's name for it, its width and height in pixels."""

    name: str
    width: int
    height: int


GEN30 = Sensor("Gen3.0", 640, 480)
GEN31 = Sensor("Gen3.1", 640, 480)
GEN40 = Sensor("Gen4.0", 1280, 720)
GEN41 = Sensor("Gen4.1", 1280, 720)
IMX636 = Sensor("IMX636", 1280, 720)
IMX646 = Sensor("IMX646", 1280, 720)
GENX320 = Sensor("GenX320", 320, 320)

SYSTEM_IDS: dict[int, tuple[Sensor, str]] = {
    # system_ID → (sensor, the encoding Metavision assumes when the header names none); the
    # ``system_id_map`` of PseeRawFileHeader::check_header, ids from devices/utils/device_system_id.h
    0x15: (GEN30, "EVT2"),  # SYSTEM_CCAM3_GEN3 (21)
    0x1C: (GEN31, "EVT2"),  # SYSTEM_CCAM3_GEN31 (28)
    0x1A: (GEN40, "EVT2"),  # SYSTEM_CCAM3_GEN4 (26)
    0x17: (GEN30, "EVT2"),  # SYSTEM_CCAM4_GEN3 (23)
    0x97: (GEN30, "EVT2"),  # SYSTEM_CCAM4_GEN3_EVK (151)
    0x19: (GEN30, "EVT2"),  # SYSTEM_CCAM4_GEN3_REV_B (25)
    0x99: (GEN30, "EVT2"),  # SYSTEM_CCAM4_GEN3_REV_B_EVK (153)
    0x1D: (GEN30, "EVT2"),  # SYSTEM_CCAM4_GEN3_REV_B_EVK_BRIDGE (29)
    0x23: (GEN31, "EVT2"),  # SYSTEM_CCAM5_GEN31 (35)
    0x1E: (GEN40, "EVT3"),  # SYSTEM_CCAM5_GEN4 (30)
    0x2E: (GEN40, "EVT3"),  # SYSTEM_CCAM5_GEN4_FIXED_FRAME (46)
    0x21: (GEN30, "EVT2"),  # SYSTEM_VISIONCAM_GEN3 (33)
    0xA1: (GEN30, "EVT2"),  # SYSTEM_VISIONCAM_GEN3_EVK (161)
    0x22: (GEN31, "EVT2"),  # SYSTEM_VISIONCAM_GEN31 (34)
    0xA2: (GEN31, "EVT2"),  # SYSTEM_VISIONCAM_GEN31_EVK (162)
    0x29: (GEN31, "EVT2"),  # SYSTEM_EVK2_GEN31 (41)
    0x1F: (GEN40, "EVT2"),  # SYSTEM_EVK2_GEN4 (31)
    0x27: (GEN41, "EVT2"),  # SYSTEM_EVK2_GEN41 (39)
    0x28: (GEN31, "EVT3"),  # SYSTEM_EVK3_GEN31_EVT3 (40)
    0x30: (GEN41, "EVT3"),  # SYSTEM_EVK3_GEN41 (48)
    0x32: (IMX636, "EVT3"),  # SYSTEM_EVK2_IMX636 (50)
    0x31: (IMX636, "EVT3"),  # SYSTEM_EVK3_IMX636 (49)
}

PLUGINS: dict[str, Sensor] = {
    # the plugins_map of hal_openeb_plugins/include/common/raw_constants.h (OpenEB 2.x) …
    "hal_plugin_gen3_fx3": GEN30,
    "hal_plugin_gen31_fx3": GEN31,
    "hal_plugin_gen31_evk2": GEN31,
    "hal_plugin_gen31_evk3": GEN31,
    "hal_plugin_gen4_fx3": GEN40,
    "hal_plugin_gen4_evk2": GEN40,
    "hal_plugin_gen41_evk2": GEN41,
    "hal_plugin_gen41_evk3": GEN41,
    # … and the IMX636 kits' plugins of hal_psee_plugins/src/plugin/CMakeLists.txt (the EVK4 header of
    # Prophesee's RAW format page names hal_plugin_imx636_evk4 with geometry 1280x720)
    "hal_plugin_imx636_evk2": IMX636,
    "hal_plugin_imx636_evk3": IMX636,
    "hal_plugin_imx636_evk4": IMX636,
}

SENSOR_NAMES: dict[str, Sensor] = {s.name: s for s in (GEN30, GEN31, GEN40, GEN41, IMX636, IMX646, GENX320)}

SENSOR_GENERATIONS: dict[str, Sensor] = {
    # "major.minor" as PseeRawFileHeader::set_sensor_info writes it; 4.2 is left out (see above)
    "3.0": GEN30,
    "3.1": GEN31,
    "4.0": GEN40,
    "4.1": GEN41,
    "320.0": GENX320,
}

PROPHESEE = "Prophesee"
SHOWN_CHARS = 80


def shown(value: str) -> str:
    """A header value as messages and sources show it: stripped, printable, at most ``SHOWN_CHARS``."""
    text = printable(value.strip())
    return text if len(text) <= SHOWN_CHARS else text[: SHOWN_CHARS - 1] + "…"


def integrator(fields: dict[str, str]) -> str:
    """Who integrated the camera, as Metavision decides it: ``plugin_integrator_name`` and
    ``camera_integrator_name``, else the older ``integrator_name``, else Prophesee; two that differ are
    shown as ``A/B`` (the tables then do not apply)."""
    plugin, camera = fields.get("plugin_integrator_name", ""), fields.get("camera_integrator_name", "")
    if not plugin and not camera:
        plugin = camera = fields.get("integrator_name", "")
    if not plugin and not camera:
        return PROPHESEE
    return plugin if plugin == camera else f"{plugin}/{camera}"


def _system_id(text: str) -> int | None:
    """The system ID as Metavision reads it (``std::stol``: leading decimal digits, the rest ignored)."""
    match = re.match(r"\s*([+-]?\d{1,18})(?!\d)", text)
    return int(match[1]) if match else None


def implied_sensor(fields: dict[str, str]) -> tuple[Sensor, str] | None:
    """The sensor the header's ``system_ID``, ``plugin_name``, ``sensor_name`` or
    ``sensor_generation`` names (tried in this order) and where it came from, e.g.
    ``(GEN41, "system_ID 48 (Gen4.1)")``; None when none is known or the integrator is not Prophesee."""
    if integrator(fields) != PROPHESEE:
        return None
    system_id = _system_id(fields.get("system_ID", "").strip())
    if system_id in SYSTEM_IDS:
        sensor = SYSTEM_IDS[system_id][0]
        return sensor, f"system_ID {shown(fields['system_ID'])} ({sensor.name})"
    plugin = fields.get("plugin_name", "").strip()
    name = plugin[: -len("_raw")] if plugin.endswith("_raw") else plugin  # OpenEB 2.x strips it too
    if name in PLUGINS:
        return PLUGINS[name], f"plugin_name {shown(plugin)} ({PLUGINS[name].name})"
    sensor_name = fields.get("sensor_name", "").strip()
    if sensor_name in SENSOR_NAMES:
        return SENSOR_NAMES[sensor_name], f"sensor_name {sensor_name}"
    generation = fields.get("sensor_generation", "").strip()
    if generation in SENSOR_GENERATIONS:
        return SENSOR_GENERATIONS[generation], f"sensor_generation {generation} ({SENSOR_GENERATIONS[generation].name})"
    return None


def implied_encoding(fields: dict[str, str]) -> str | None:
    """The encoding Metavision assumes for a header without ``% format`` or ``% evt``: the one its
    system_ID table gives (Prophesee integrator only)."""
    if integrator(fields) != PROPHESEE:
        return None
    system_id = _system_id(fields.get("system_ID", "").strip())
    return SYSTEM_IDS[system_id][1] if system_id in SYSTEM_IDS else None


def unknown_identity(fields: dict[str, str]) -> str:
    """What the header says of its camera that the tables do not know, for an error message
    ("system_ID 99, plugin_name hal_plugin_x"; "integrator Acme: …"), or "" when it says nothing."""
    who = integrator(fields)
    keys = ("system_ID", "plugin_name", "sensor_name", "sensor_generation")
    named = ", ".join(f"{k} {shown(fields[k])}" for k in keys if fields.get(k, "").strip())
    if who != PROPHESEE:
        return f"integrator {shown(who)}: Prophesee's sensor tables do not apply" + (f" to {named}" if named else "")
    return f"{named}: not in the sensor tables" if named else ""
