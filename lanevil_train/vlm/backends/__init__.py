"""The VLM backends: HFVLM (any Hugging Face image-text-to-text model, hf.py), OpenAIVLM (an OpenAI-compatible
server, openai.py), the embedded VLM built and trained here (embedded.py), and the whole-file checks a saved model's
weights pass before they load (weight_files.py)."""
