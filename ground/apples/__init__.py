"""Apples: detections linked across frames into apples (association, geometry, the paper's method) and apples split into rows (rows)."""
