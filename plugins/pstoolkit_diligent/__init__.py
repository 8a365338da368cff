"""First-party plugin: the DiLiGenT and DiLiGenT-Π converters (``pstoolkit convert diligent|diligent-pi``).

The import sits inside the hook, so the command line starts without loading this plugin's modules.
"""

from __future__ import annotations

from pstoolkit import Registry, hookimpl


@hookimpl
def pstoolkit_register_converters(registry: Registry) -> None:
    from pstoolkit_diligent.converters import DiLiGenT, DiLiGenTPi

    for converter in (DiLiGenT, DiLiGenTPi):
        registry.register(converter)
