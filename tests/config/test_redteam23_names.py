"""Red team 23: the config's own name patterns (a principal's name, an environment
variable's, the bridge's node name) ended in a bare `$`, which Python (and so msgspec's
pattern check) also matches before a final newline — the trap `rcan._types.whole` was made
for. `"admin\\n"` loaded beside `admin` as a second principal of another role: one name as
the audit log and the console show it, two roles (the case rule of red team 22 does not see
it)."""

from __future__ import annotations

import pytest

from rcan_rtps.config import ConfigError, loads_config
from tests.config.test_redteam22_config import _config


@pytest.mark.parametrize(("principals", "extra", "where"), [
    ('      - {name: "admin\\n", role: GUEST, token_env: RT_OTHER}', "",
     "$.bridge.api.principals[2].name"),
    ('      - {name: other, role: GUEST, token_env: "RT_OTHER\\n"}', "",
     "$.bridge.api.principals[2].token_env"),
    ("", '  ros2: {node_name: "rcan_bridge\\n"}', "$.bridge.ros2.node_name"),
])
def test_a_name_ending_in_a_newline_is_refused(principals: str, extra: str,
                                               where: str) -> None:
    with pytest.raises(ConfigError) as info:
        loads_config(_config(extra, principals), env={})
    assert [issue.path for issue in info.value.issues] == [where]
