"""First-party plugin that registers pstoolkit's built-in light models, BRDFs and scenes."""
