"""Thin ComfyUI node classes; every algorithm lives in physmotion_core."""
