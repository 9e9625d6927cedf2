import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sim  # noqa: E402,F401  (selects the GL backend before mujoco is imported)
import tether.catalog  # noqa: E402,F401  (registers the built-in strategies and scenarios)
