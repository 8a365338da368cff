pytest_plugins = ["pstoolkit.testing"]
