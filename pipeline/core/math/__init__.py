"""Mathematics and reference values: rotations, frames, constants, tiling, random streams."""
