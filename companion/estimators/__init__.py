"""Estimators the daemon can run: georef, terrain_lba, vis_thermal_ekf."""
