"""Event cameras: the sensor's event rule and the EventPS relation between events and normals."""
