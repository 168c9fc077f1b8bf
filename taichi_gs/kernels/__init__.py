"""Every line of Taichi in taichi-gs lives in this package; nothing outside imports taichi."""

import os

# Taichi prints a version banner on stdout when imported; stdout carries results (`info`, `--json`).
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
