"""The simulator: scenes, the renderer, the event engines and the capture writer."""
