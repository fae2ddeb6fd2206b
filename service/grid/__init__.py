"""Planner-ready output: image maps projected onto a ground grid and fused over time (numpy only)."""
