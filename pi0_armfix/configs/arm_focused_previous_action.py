"""The project's fix (`arm_focused`) with its joint groups relative to the action commanded one
frame before instead of the state (`data.delta_reference = 'previous_action'`): what holding the
previous action knows, given to the policy. Where a command sits at a steady offset from the
measured position (a real arm's controller error; docs/mechanisms.md, the G1), the state alone
cannot give the offset and holding the previous action carries it; relative to the previous
command, holding is the policy's zero. At inference the policy needs the last commanded action:
the closed loop and the harness pass the one they executed, a server's client sends it
(`previous_action`).

  python -m pi0_armfix.train --config=configs/arm_focused_previous_action.py:g1 \
      --config.data.root=<a G1 root>
"""

from pi0_armfix.configs import arm_focused


def get_config(arg=None):
    config = arm_focused.get_config(arg)
    config.data.delta_reference = "previous_action"
    return config
