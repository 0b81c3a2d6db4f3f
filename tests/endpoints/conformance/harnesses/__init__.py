"""One module per protocol of the registry, named after it, each exposing ``HARNESS``."""
