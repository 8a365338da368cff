"""Event cameras: the sensor's event rule (``rule``) and the relation between events and normals that the event solvers share (``relation``)."""
