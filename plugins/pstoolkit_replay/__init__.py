"""First-party plugin: the `replay` backend that plays a capture file as if it were the rig."""
