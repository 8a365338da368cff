"""The plugin machinery: hook specifications, the plugin manager, registries and typed options."""
