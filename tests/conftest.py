import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import softbody  # noqa: E402,F401  (turns on float64 before any test builds arrays)
