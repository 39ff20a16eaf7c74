"""The bottom tier: shared checks, grids and units, colour constants and XLA helpers.

Every other tier may import from here; nothing here imports from the rest of invglare
except :mod:`invglare.errors`.
"""
