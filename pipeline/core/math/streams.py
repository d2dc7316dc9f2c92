"""The run's random streams: one registry of the tags that keep them apart within a seed (the run
seed, or a section's own: the world's, the terrain's, the map's).

Every random draw of a run comes from `stream(seed, purpose, *keys)`: a PCG64 generator seeded by
`SeedSequence(seed, spawn_key=(TAGS[purpose], *keys))`, keys such as the frame number making a
stream per sample, so that a draw depends only on the seed, its purpose and its own keys, never on
the order of processing, the window of frames asked for or the number of workers. A new purpose
is a new entry here (the tags are distinct, and a test checks it).
"""

from __future__ import annotations

import numpy as np

TAGS: dict[str, int] = {
    "detection": 0xDE7EC7,  # per frame: identify, match, select, noise, detect, false, star, verify
    "estimation": 0xE57,  # per frame and method: the robust estimator's RANSAC draws
    "imu": 0x1A1,  # the IMU's turn-on errors, bias histories and noise
    "altimeter": 0xA17,  # the laser altimeter's noise
    "init": 0x1417,  # the navigation filter's initial-state dispersion
    "rough_position": 0x1D5,  # lost in space: the rough position's error
    "rough_velocity": 0x1D6,  # lost in space: the rough velocity a fix starts the filter with
    "render": 0x12E4D,  # per frame: the rendered surface's roughness and the sensor's noise
    "velocimeter": 0xD0F,  # the Doppler velocimeter's noise (the closed loop)
    "hazard_lidar": 0x4A2D,  # the hazard lidar's range noise (the closed loop)
    # the world's, each within its own section's seed
    "degradation": 0xD17F,  # each world crater's normalised age (detection.world_seed)
    "terrain_base": 0xBA5E,  # the synthetic long-wavelength base (terrain.seed)
    "terrain_roughness": 0x7E4,  # the roughness' octave rotations, offsets, keys (terrain.seed)
    "map": 0x3A9,  # the flight map's drawn shift and bias (map.seed)
}


def seed_sequence(seed: int, purpose: str, *keys: int) -> np.random.SeedSequence:
    """The SeedSequence of one purpose (a key of TAGS) and its keys within the run seed."""
    return np.random.SeedSequence(seed, spawn_key=(TAGS[purpose], *keys))


def stream(seed: int, purpose: str, *keys: int) -> np.random.Generator:
    """The generator of one purpose (a key of TAGS) and its keys within the run seed."""
    return np.random.Generator(np.random.PCG64(seed_sequence(seed, purpose, *keys)))
