"""First-party plugin: the serial ring-light hardware backend."""
