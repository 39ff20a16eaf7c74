import os

# Tests run on the CPU with float32 by default; float64 is enabled locally with helpers.x64().
os.environ.setdefault("JAX_PLATFORMS", "cpu")
