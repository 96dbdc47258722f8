"""Blender (bpy, Cycles) rendering of scenes with exact intrinsics, shading and light balls.

`spec` is pure numpy and importable anywhere; the other modules import bpy and run only in a
Python that has the bpy module (Python 3.11, bpy 5.0.x).
"""
