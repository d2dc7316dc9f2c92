"""What a campaign's dispersions reach: the base with the overrides is a valid config, and every
dispersed value can change what the runs compute up to the campaign's target, else the spec is
refused at load naming it (a dispersion that changes nothing would be reported as one, its
identical runs counted as independent in the percentiles):
- some stage up to the target, active for the config, reads the key (`Stage.reads_for`; what only
  visuals read changes no table);
- the paper's sensor reads none of the physical sensor's fields (`PHYSICAL_ONLY`);
- the world's seed needs a world error (a catalogue or site-map sigma > 0); an option of an
  instrument that is off, of a map or terrain that is not there, of a step that does not run
  (the jitter's seed without jitter, the robust step's options without it, ...) is not read
  (`RunConfig.ignored`, unless what decides it is dispersed too);
- a sweep grid repeats no value, a normal has sigma > 0 and a uniform high > low (checked with
  the spec's keys in `spec`).
A key is judged on the base with the overrides and on each value of every grid and choice (a
dispersed sensor makes its fields count): read in one of them is enough.
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING, Any

from pipeline.config import RunConfig, load_config
from pipeline.config.detection import PHYSICAL_ONLY
from pipeline.errors import ConfigError

if TYPE_CHECKING:
    from pipeline.campaign.spec import Dispersion

WORLD_SIGMAS = ("catalogue_sigma_horizontal_m", "catalogue_sigma_height_m",
                "catalogue_sigma_diameter_share", "site_map_sigma_horizontal_m",
                "site_map_sigma_height_m", "site_map_relative_sigma_m")
RENDER_WINDOW = ("start_s", "end_s")  # the render section's fields that choose what is drawn


def check_base(base: str, overrides: dict[str, Any], dispersions: tuple[Dispersion, ...],
               flags: dict[str, bool], mounting_deg: float, target: str) -> RunConfig:
    """The base with the overrides is a valid config, and a built-in dispersion changes the runs:
    a seed or angle the config ignores would be drawn, recorded and silently not applied (the
    catalogue errors and the mounting need the physical sensor, the catalogue errors a non-zero
    sigma, the jitter seed a non-zero rate); so does every other dispersion (`check_reach`).
    Returns the base with the overrides (the campaign's config: its table window, its mounting)."""
    dispersed = {d.key for d in dispersions}
    try:
        cfg = load_config(base, "campaign-base", overrides)
    except ConfigError as exc:
        raise ConfigError(f"base and overrides: {exc}") from None
    d, physical = cfg.detection, cfg.detection.sensor == "physical"
    if mounting_deg > 0 and not physical:
        raise ConfigError(f"mounting_sigma_deg = {mounting_deg:g}: the camera mounting needs "
                          f"detection.sensor = \"physical\" (the base and overrides give "
                          f"{d.sensor!r}: the paper's camera is the body frame)")
    sigmas = WORLD_SIGMAS
    if flags["catalogue_errors"] and not (physical and (
            any(getattr(d, k) > 0 for k in sigmas)
            or any(f"detection.{k}" in dispersed for k in sigmas))):
        raise ConfigError("catalogue_errors = true: the catalogue's errors (detection.world_seed) "
                          "need detection.sensor = \"physical\" and a catalogue sigma > 0 "
                          f"(detection.{sigmas[0]}, ...); the base and overrides give sensor "
                          f"{d.sensor!r}, sigmas {[getattr(d, k) for k in sigmas]}: the draw "
                          "would change nothing")
    rate = "trajectory.jitter_rate_sigma_rad_s"
    if flags["jitter"] and cfg.trajectory.jitter_rate_sigma_rad_s == 0 and rate not in dispersed:
        raise ConfigError(f"jitter = true: the pointing jitter's seed needs {rate} > 0 (the base "
                          "and overrides give 0: the draw would change nothing)")
    if mounting_deg > 0 and cfg.identification.mode != "simulated":
        raise ConfigError(f"mounting_sigma_deg = {mounting_deg:g}: a mounting the navigator does "
                          "not know needs identification.mode = \"simulated\" (the base and "
                          f"overrides give {cfg.identification.mode!r})")
    check_reach(base, overrides, dispersions, cfg, target)
    return cfg




def set_dotted(d: dict[str, Any], key: str, value: Any) -> None:
    """Set dotted `key` of the nested tables `d` (its tables made as needed)."""
    *parents, last = key.split(".")
    for p in parents:
        d = d.setdefault(p, {})
    d[last] = value


def _variants(base: str, overrides: dict[str, Any], dispersions: tuple[Dispersion, ...],
              cfg: RunConfig) -> list[RunConfig]:
    """The base with the overrides, and with each value of each grid and choice (those values
    that make a valid config)."""
    out = [cfg]
    for d in dispersions:
        if d.kind not in ("grid", "choice"):
            continue
        for value in d.values:
            over = copy.deepcopy(overrides)
            set_dotted(over, d.key, value)
            try:
                out.append(load_config(base, "campaign-base", over))
            except ConfigError:
                continue  # a run with that value is recorded invalid_config
    return out


def why_ignored(cfg: RunConfig, key: str, target: str, dispersed: set[str]) -> str | None:
    """Why a run of `cfg` brought up to stage `target` computes nothing differently for another
    value of config `key`; None when some stage reads it."""
    from pipeline.stages import DAG  # the stages' declarations (the campaign sits above them)

    d = cfg.detection
    section, _, name = key.partition(".")
    if section == "detection" and name in PHYSICAL_ONLY and d.sensor != "physical":
        return (f"the paper's sensor does not read it (detection.sensor = {d.sensor!r}; it is a "
                "field of the physical sensor)")
    if key == "detection.world_seed" and not (
            any(getattr(d, k) > 0 for k in WORLD_SIGMAS)
            or any(f"detection.{k}" in dispersed for k in WORLD_SIGMAS)):
        return (f"the world has no errors to draw (detection.{WORLD_SIGMAS[0]}, ... are all 0): "
                "the world's seed changes nothing")
    if (section == "render" and name not in RENDER_WINDOW and cfg.render.start_s is None
            and not dispersed & {f"render.{k}" for k in RENDER_WINDOW}):
        return ("no frame is rendered (render.start_s and end_s unset): the renderer's options "
                "change nothing")
    if (section == "identification" and name != "mode" and cfg.identification.mode == "simulated"
            and "identification.mode" not in dispersed):
        return ("identification is simulated (identification.mode = 'simulated': a draw at "
                "detection.p_identify): the algorithms' options change nothing")
    found = cfg.ignored(key)
    if found is not None and not set(found[1]) & dispersed:
        return found[0]
    stages = [s for s in DAG.upstream_closure([target], cfg) if DAG.is_active(s, cfg)]
    for s in stages:
        for path in DAG[s].reads_for(cfg):
            if key == path or key.startswith(path + ".") or path.startswith(key + "."):
                return None
    return f"no stage up to target {target!r} reads it (the runs run {stages})"


def check_reach(base: str, overrides: dict[str, Any], dispersions: tuple[Dispersion, ...],
                cfg: RunConfig, target: str) -> None:
    """Every dispersion can change what the runs compute (in some variant of the config), else
    ConfigError naming it and why."""
    if not dispersions:
        return
    variants = _variants(base, overrides, dispersions, cfg)
    dispersed = {d.key for d in dispersions}
    for disp in dispersions:
        reasons = [why_ignored(v, disp.key, target, dispersed) for v in variants]
        if all(reasons):
            where = f"dispersions.{disp.key!r}" if "." in disp.key else f"dispersions.{disp.key}"
            raise ConfigError(f"{where}: a dispersion that changes nothing: {reasons[0]}")
