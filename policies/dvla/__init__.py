"""The action-token model family: one transformer, its checkpoints and training recipes,
and the decoders (bidirectional, block diffusion, Fast-dLLM, Fast-dVLA, autoregressive)
that turn it into policies. Kept apart from the scripted experts so that nothing here
depends on a simulator."""
