"""Pure `torch.nn` models (no Lightning): tokenizer, transformers, heads."""
