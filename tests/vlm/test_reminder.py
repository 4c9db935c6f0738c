"""Self-Reminder: every question reaches the model between the two reminders, for answers and losses alike."""

from __future__ import annotations

import pytest
import torch

from lanevil_train.vlm.base import VLM
from lanevil_train.vlm.defenses.reminder import DRIVING, ORIGINAL, RemindedVLM, remind


class Recording(VLM):
    """A VLM that answers with the question it was asked."""

    name = "echo"

    def answer(self, clips, questions):
        return list(questions)


def test_the_question_sits_between_the_reminders():
    wrapped = remind("Is the road wet?")
    assert wrapped == f"{DRIVING[0]}\nIs the road wet?\n{DRIVING[1]}"
    assert wrapped.startswith("You should be a responsible driving assistant")
    assert ORIGINAL[0].startswith("You should be a responsible ChatGPT") and ORIGINAL[1].startswith("Remember,")


def test_every_answer_and_streamed_answer_is_to_the_wrapped_question():
    reminded = RemindedVLM(Recording(), "Be careful!", "Remember to be careful!", name="echo+self_reminder")
    clips = [[None], [None]]
    assert reminded.answer(clips, ["A?", "B?"]) == ["Be careful!\nA?\nRemember to be careful!",
                                                   "Be careful!\nB?\nRemember to be careful!"]
    assert dict(reminded.answer_stream(clips, ["A?"])) == {0: "Be careful!\nA?\nRemember to be careful!"}
    assert reminded.name == "echo+self_reminder"
    assert reminded.identity() == {"backend": "Recording", "name": "echo",
                                   "reminder": ["Be careful!", "Remember to be careful!"]}
    with pytest.raises(ValueError, match="defense.after: expected the reminder sentence"):
        RemindedVLM(Recording(), "Be careful!", " ")


def test_the_answer_loss_is_the_models_on_the_wrapped_question(tiny_hf_vlm, small_clips):
    vlm = tiny_hf_vlm("llava")
    reminded = RemindedVLM(vlm)
    questions, answers = ["Is it wet?", "How many lanes?"], ["Yes.", "Three."]
    with torch.no_grad():
        got = reminded.answer_loss(small_clips, questions, answers)
        expected = vlm.answer_loss(small_clips, [remind(q) for q in questions], answers)
        plain = vlm.answer_loss(small_clips, questions, answers)
    assert torch.allclose(got, expected) and not torch.allclose(got, plain)
