"""The deploy's I/O: what a deploy asks of the world besides the Kubernetes API (registries)."""
