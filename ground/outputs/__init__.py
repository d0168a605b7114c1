"""Outputs: the map files a grower opens (tables: CSV, GeoJSON, PLY, report) and the rerun recording (rerun_log)."""
