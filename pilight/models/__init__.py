"""Inference models built from their saved config (config.json + model.safetensors): stage 1's
IntrinsicsModel and stage 2's RelightModel, their DiffusionStack, and the model folder's files. Nothing here
imports training, shards or Blender (.importlinter): the photo API, the infer_intrinsics and relight
stages and the trade sweep stand on it, and training builds its Tasks on it."""
