"""Built-in model files, addressable by name wherever a model path is accepted."""
