"""Luxonis ToF cameras through DepthAI v3 (device and host-only pipelines)."""
