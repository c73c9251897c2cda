"""Under ``jax.set_mesh`` the fast kernels split their lanes over the mesh's devices.

The checks (``tests/kernels/devices_check.py``) run in a child process with two CPU devices, since
the device count is fixed when JAX starts; each compares the split call with the same call
without a mesh (values and gradients), and reads the lowered program for the split.
"""

import os
import subprocess
import sys
from pathlib import Path

CHECK = Path(__file__).with_name("devices_check.py")


def test_lanes_split_over_a_mesh_give_the_single_device_results():
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, str(CHECK)], capture_output=True, text=True, env=env, timeout=900
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-6000:]
    ok = [line for line in out.stdout.splitlines() if line.startswith("OK ")]
    # 7 cases at 32 lanes (split), 2 at 33 (not split), 2 under an Explicit mesh, 2 with
    # sharded inputs and no mesh set, 4 single sequences with their time axis split
    assert len(ok) == 17, out.stdout
