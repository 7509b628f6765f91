"""The routers' Zenoh configs of a manifest deployment (deploy/access.py) as Zenoh itself reads them:
fixed router ids, and publications between hosts overwritten to be dropped rather than block."""
from __future__ import annotations

import json

import zenoh

from deploy import access
from deploy.manifest import load_manifest
from deploy.router import free_port


def _manifest(tmp_path, security: str):
    (tmp_path / "scenario.toml").write_text("")
    path = tmp_path / "deployment.toml"
    path.write_text(f'''name = "pair"
scenario = "scenario.toml"
security = "{security}"
[hosts.robot]
listen = "tcp/127.0.0.1:{free_port()}"
services = ["bridge", "localizer", "controller"]
links = ["learning"]
[hosts.learning]
listen = "tcp/127.0.0.1:{free_port()}"
services = ["gp_store", "scheduler"]
''')
    return load_manifest(path)


def test_each_router_has_a_fixed_id_and_drops_rather_than_blocks_toward_the_other_host(tmp_path):
    m = _manifest(tmp_path, "none")
    ids = {h: access.router_zid(m, h) for h in ("robot", "learning")}
    assert len(set(ids.values())) == 2 and all(len(z) == 32 and z[0] != "0" for z in ids.values())
    assert access.router_zid(m, "robot") == ids["robot"]          # the same every time it is written
    for host, other in (("robot", "learning"), ("learning", "robot")):
        conf = access.router_config(m, host, "r1")
        (rule,) = conf["qos"]["network"]
        assert conf["id"] == ids[host] and rule["zids"] == [ids[other]]
        assert rule["flows"] == ["egress"] and "put" in rule["messages"]
        assert rule["overwrite"] == {"congestion_control": "drop"}
        # Zenoh accepts it as a router's config and takes the id
        session = zenoh.open(zenoh.Config.from_json5(json.dumps(dict(conf, connect={"endpoints": []}))))
        try:
            assert str(session.zid()) == ids[host]
        finally:
            session.close()
