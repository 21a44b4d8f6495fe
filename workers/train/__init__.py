"""The train worker: rendered images become a detector ω and its score P. Never imports bpy."""

import os

# OpenMP threads that spin while waiting for work steal the cores other processes (render
# workers, a second trainer) need: on 2 shared cores, spinning made training up to 28× slower.
# Must be set before torch loads its OpenMP runtime; a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
