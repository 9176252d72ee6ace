"""Model compression: label-free distillation and structured pruning of trained variants."""
