"""Event data: readers, the synthetic egocentric generator, and prepared LNES caches."""
