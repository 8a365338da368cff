"""The toolkit's version (the one ``pyproject.toml`` declares), written into the captures and results it makes."""

__version__ = "0.1.0"
