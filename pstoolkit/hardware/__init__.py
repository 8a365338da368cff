"""Hardware: the light-rig and camera backend interface, event→frame calibration."""
