"""Clips and their QA: 6-frame clips rendered from the simulator (clips.py), their questions and answers (qa.py the
open ones and the truth checks, qa_closed.py the closed ones, qa_facts.py their words, qa_records.py a record and the
accuracy rule), planned per suite so no wording gives its answer away (suite_qa.py), clip suites on disk or rendered
on the fly (clip_set.py), the DriveLM layout (drivelm.py), the optional paraphrasing pass over QA texts
(paraphrase.py) and the (clip, QA) pairs fine-tuning reads (qa_data.py)."""
