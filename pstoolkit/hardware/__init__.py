"""Hardware: the light-rig and camera backend interface, event→frame calibration, and light
calibration from a chrome sphere (``lightcal``: the registry's kind; ``sphere``, ``highlight``:
geometry and highlights; ``sphere_frames``, ``sphere_events``: the built-in methods; ``ringfit``)."""
