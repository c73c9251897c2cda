"""Test configuration: the suite runs in float64 (the library itself never flips the flag);
float32 behaviour is checked with explicitly float32 inputs."""

import jax

jax.config.update("jax_enable_x64", True)
