"""Fine-tuning a VLM on clip QA: the LightningModule (finetune.py: VLMFineTuner, LoRA, visual defenses), sharded
training for big models (sharding.py: FSDP, DeepSpeed) and where a VLM's vision tokens lie on the frames
(vision_maps.py, for AAM / AAM++)."""
