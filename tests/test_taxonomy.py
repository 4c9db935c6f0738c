"""The illusion taxonomy has one source: the renderers' registry and the reports read the same table."""

from __future__ import annotations

from lanevil_train import taxonomy
from lanevil_train.illusions import CATEGORIES, ILLUSIONS, SEVERITIES
from lanevil_train.report.records import categories_of, illusions_of


def test_registry_reads_the_taxonomy_table():
    assert CATEGORIES is taxonomy.CATEGORIES and SEVERITIES is taxonomy.SEVERITIES
    assert tuple(ILLUSIONS) == taxonomy.ILLUSION_NAMES  # every illusion registered, in the paper's order
    assert {name: ill.category for name, ill in ILLUSIONS.items()} == dict(taxonomy.ILLUSION_CATEGORY)
    assert len(taxonomy.ILLUSION_NAMES) == 14 and len(CATEGORIES) == 4


def test_reports_order_by_the_same_table():
    records = [{"severity": 1, "illusion": name, "category": taxonomy.ILLUSION_CATEGORY[name]}
               for name in reversed(taxonomy.ILLUSION_NAMES)]
    assert illusions_of(records) == list(taxonomy.ILLUSION_NAMES)
    assert categories_of(records) == list(taxonomy.CATEGORIES)
