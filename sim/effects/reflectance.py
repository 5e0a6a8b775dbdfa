"""The scene-stage effect of the materials: NIR reflectance differing from the scene file's."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from tofhil.errors import InputFileError
from tofhil.sim.effects.base import Effect, Param, _same_values
from tofhil.sim.effects.registry import register


@register
class ReflectanceEffect(Effect):
    name = "reflectance"
    stage = "scene"
    rank = 30
    summary = "NIR reflectance differing from the file's (diffuse, glossy and checker values scaled); options `materials: {name: factor}`, `objects: {name: factor}`"
    doc = ("NIR reflectance different from the scene file's: every material's diffuse and glossy "
           "reflectance (and checker texture values) times `scale`, and per material or per object "
           "times the factors in `materials: {name: factor}` / `objects: {name: factor}`.")
    params = {"scale": Param(1.0, 0.0, 20.0, "", "factor on every material's reflectance",
                             fit=(0.05, 20.0), step=0.02)}
    options = {"materials": "mapping material name -> reflectance factor",
               "objects": "mapping object name -> reflectance factor (the object gets its own material)"}

    def check_options(self, values: dict[str, Any], *, source: str | Path, prefix: str) -> None:
        for key in ("materials", "objects"):
            m = values.get(key)
            if m is None:
                continue
            if not isinstance(m, Mapping):
                raise InputFileError(f"got {m!r}", file=source, field=f"{prefix}.{key}",
                                     expected="a mapping name -> factor")
            for name, fac in m.items():
                if isinstance(fac, bool) or not isinstance(fac, (int, float)) or not 0 <= fac <= 20:
                    raise InputFileError(f"got {fac!r}", file=source, field=f"{prefix}.{key}.{name}",
                                         expected="a factor in [0, 20]")

    def is_off(self, values: Mapping[str, Any]) -> bool:
        factors = list((values.get("materials") or {}).values()) + list((values.get("objects") or {}).values())
        return float(values.get("scale", 1.0)) == 1.0 and all(f == 1 for f in factors)

    @staticmethod
    def _scaled(mat: Any, s: float, name: str | None = None) -> Any:
        tex = mat.texture
        if tex is not None and tex.kind == "checker":
            tex = dataclasses.replace(tex, values=tuple(v * s for v in tex.values))
        return dataclasses.replace(mat, name=name or mat.name, reflectance=mat.reflectance * s,
                                   glossy_reflectance=mat.glossy_reflectance * s, texture=tex)

    def apply_scene(self, scene: Any, values: Mapping[str, Any]) -> Any:
        scale = float(values.get("scale", 1.0))
        per_mat = dict(values.get("materials") or {})
        per_obj = dict(values.get("objects") or {})
        for name in per_mat:
            if name not in scene.materials:
                raise InputFileError(f"no material {name!r} in the scene", file=scene.source,
                                     field=f"effects.reflectance.materials.{name}",
                                     expected="one of " + ", ".join(scene.materials))
        names = [o.name for o in scene.objects]
        for name in per_obj:
            if name not in names:
                raise InputFileError(f"no object {name!r} in the scene", file=scene.source,
                                     field=f"effects.reflectance.objects.{name}",
                                     expected="one of " + ", ".join(names))
        mats = {k: self._scaled(m, scale * float(per_mat.get(k, 1.0))) for k, m in scene.materials.items()}
        objects = list(scene.objects)
        for i, o in enumerate(objects):
            if o.name in per_obj:
                own = f"{o.material}@{o.name}"
                mats[own] = self._scaled(mats[o.material], float(per_obj[o.name]), own)
                objects[i] = dataclasses.replace(o, material=own)
        return dataclasses.replace(scene, materials=mats, objects=objects)

    def rescale_render(self, result: Any, values: Mapping[str, Any], rendered: Mapping[str, Any],
                       scene: Any) -> Any | None:
        """Light that reflected n times scales as ``s^n``: exact for the direct light (n = 1) and
        one bounce (n = 2) when every material scales alike (the renderer's paths do not depend
        on the reflectance); a render with more bounces, per-material factors, a transient or a
        zero reference needs a new render."""
        if _same_values(values, rendered):
            return result
        s_new, s_ref = float(values.get("scale", 1.0)), float(rendered.get("scale", 1.0))
        same_options = all(dict(values.get(k) or {}) == dict(rendered.get(k) or {}) for k in ("materials", "objects"))
        if not same_options or s_ref <= 0.0 or result.transient is not None or result.bounces > 1:
            return None
        s = s_new / s_ref
        changes: dict[str, Any] = {"ambient_power_w": result.ambient_power_w * s}
        if result.ambient_power_per_irradiance is not None:
            changes["ambient_power_per_irradiance"] = result.ambient_power_per_irradiance * s
        if result.bounces == 0:
            changes.update(phasor=result.phasor * s, power_w=result.power_w * s)
            if result.phasor_direct is not None:
                changes.update(phasor_direct=result.phasor_direct * s, phasor_indirect=result.phasor_indirect * s)
            return dataclasses.replace(result, **changes)
        freq = np.asarray(result.freq_hz)
        zero = np.flatnonzero(freq == 0.0)
        if result.phasor_direct is None or result.phasor_indirect is None or not zero.size:
            return None  # the direct/indirect split of the power is unknown
        direct, indirect = result.phasor_direct * s, result.phasor_indirect * (s * s)
        p_direct = result.phasor_direct[zero[0], tuple(result.harmonics).index(1)].real
        changes.update(phasor_direct=direct, phasor_indirect=indirect, phasor=direct + indirect,
                       power_w=s * p_direct + (s * s) * (result.power_w - p_direct))
        return dataclasses.replace(result, **changes)
