"""Run arraysel's selector conformance suite on the example plugin."""
from arraysel.testing import SelectorConformance

from arraysel_example_plugin import SwapSelector


class TestSwapConformance(SelectorConformance):
    selector_class = SwapSelector
    selector_options = {"batch": 8}
