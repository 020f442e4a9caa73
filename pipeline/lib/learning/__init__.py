"""Learning: BoTER, the SPI loss, training, the checkpoint, the split, metrics, ONNX,
sweeps and ablations, validation on independent campaigns, the model's workspace."""
