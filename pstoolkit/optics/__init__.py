"""Light and reflectance: light models, equivalent lights of an exposure, light layouts, BRDFs."""
