"""Scripted experts that act from privileged simulator state: the upper bounds of each
suite and the source of the demonstrations the model family is trained on."""
