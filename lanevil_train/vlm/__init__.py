"""Driving vision-language models, around one contract (base.py: VLM) that every part uses:
backends/ (the models: Hugging Face, OpenAI-compatible servers, the embedded VLM), clips/ (clips and QA from the
simulator), training/ (fine-tuning), defenses/ (the textual defenses: PAT++, PAT, Self-Reminder) and answer_scoring/
(answer evaluation, judges). http.py is the chat-completions client the OpenAI backend, the judges and the
paraphraser share; tokenizer.py trains the offline BPE tokenizers (the embedded VLM's). Backends import their
heavy libraries (transformers, HTTP) only when built."""
