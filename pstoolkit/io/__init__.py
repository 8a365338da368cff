"""Files the toolkit reads and writes besides the capture format: normal maps, DiLiGenT folders,
converters, folders written as a unit."""
