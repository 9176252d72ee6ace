"""Model compression: structured pruning (prune, surgery, latency model) and distillation."""
