"""Shared core: errors, configuration, state layout, HDF5 schema, atomic I/O.

Imports neither torch nor dolfinx, so every stage (and every device plugin) can use it.
"""
