"""The rendered images' section (stage `render`)."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.config.checks import PROPAGATION_LIMIT_S, _check, _num

RENDER_DETECTORS = ("classical", "learned")


@dataclass(frozen=True)
class RenderConfig:
    """Rendered camera images (stage `render`): which frames, the terrain's roughness and the
    sensor; the craters come from the world (the catalogue with its errors), the camera and the
    Sun from `detection` and `trajectory`."""

    start_s: float | None  # first frame rendered (s); None: no image
    end_s: float | None  # last frame rendered (s, inclusive)
    stride: int  # every stride-th frame of the window
    roughness_rms_slope_deg: float  # fractal roughness: RMS slope over one ground pixel
    albedo: float  # normal albedo of the Lunar-Lambert function
    read_noise_e: float
    full_well_e: float
    bits: int
    blur_sigma_px: float
    recording_size_px: int  # side of the recording's images (JPEG)
    detector: str  # classical | learned (`pipeline.ops.detectors`)

    def __post_init__(self) -> None:
        k = "render."
        _check((self.start_s is None) == (self.end_s is None), k + "end_s",
               "give both start_s and end_s, or neither")
        if self.start_s is not None and self.end_s is not None:
            _num(self.start_s, k + "start_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
            _num(self.end_s, k + "end_s", 0.0, PROPAGATION_LIMIT_S, unit="s")
            _check(self.end_s >= self.start_s, k + "end_s",
                   f"= {self.end_s:g} s must be >= start_s ({self.start_s:g} s)")
        _num(self.stride, k + "stride", 1, 1_000_000)
        _num(self.roughness_rms_slope_deg, k + "roughness_rms_slope_deg", 0.0, 30.0, unit="deg")
        # the Moon's normal albedo is 0.07-0.16 (maria to highlands); the exposure is fixed (full
        # well at I/F 0.2), so a much brighter surface saturates
        _num(self.albedo, k + "albedo", 0.02, 0.3)
        _num(self.read_noise_e, k + "read_noise_e", 0.0, 1e4, unit="e-")
        _num(self.full_well_e, k + "full_well_e", 100.0, 1e7, unit="e-")
        _num(self.bits, k + "bits", 8, 16)
        _num(self.blur_sigma_px, k + "blur_sigma_px", 0.0, 10.0, unit="px")
        _num(self.recording_size_px, k + "recording_size_px", 64, 4096, unit="px")
        _check(self.detector in RENDER_DETECTORS, k + "detector",
               f"= {self.detector!r}: must be one of {RENDER_DETECTORS}")

    @property
    def enabled(self) -> bool:
        return self.start_s is not None
