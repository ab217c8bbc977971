"""Upload -> job -> events -> succeeded -> policy download, through the real API, PostgreSQL, Redis and a worker;
a second job on the same data and seed reuses the first one's dynamics ensemble from the shared model cache."""
from __future__ import annotations

import io

import torch

from kernel.storage import job_dir


def test_upload_train_download(alice, worker, hopper_file, settings):
    ds = alice.api.upload_dataset(hopper_file)
    assert ds["object"] == "dataset" and ds["env"] == "hopper" and ds["name"] == hopper_file.name
    assert ds["report"]["transitions"] == 2000 and (ds["obs_dim"], ds["act_dim"]) == (11, 3)
    assert ds["report"]["terminals"] + ds["report"]["timeouts"] >= 1
    import hashlib
    assert ds["sha256"] == hashlib.sha256(hopper_file.read_bytes()).hexdigest()

    r = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "algorithm": "drop", "preset": "smoke", "seed": 1,
                                     "overrides": {"dice.lr": 1e-3}})
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["status"] == "queued" and job["env"] == "hopper" and job["config"]["dice"]["lr"] == 1e-3

    done = alice.api.wait(job["id"], timeout=120)
    assert done["status"] == "succeeded", done
    assert done["attempts"] == 1 and done["progress"]["fraction"] == 1.0
    assert done["best_score"] is not None and done["last_score"] is not None
    assert "sac/critic_loss" in done["latest_metrics"]
    # The job names its ensemble, which is in the model cache under the data directory (an earlier test may have put
    # it there first); the server's path to it is not shown.
    dynamics = done["dynamics"]
    assert (settings.data_dir / "models" / f"{dynamics['cache_key']}.pt").is_file() and "cache_path" not in dynamics
    assert isinstance(dynamics["from_cache"], bool) and done["latest_metrics"]["dynamics/from_cache"] == float(
        dynamics["from_cache"])
    fit = done["config"]["dynamics"]
    assert (len(dynamics["holdout_mse"]), len(dynamics["elites"])) == (fit["members"], fit["elites"])
    assert 1 <= dynamics["epochs"] <= fit["max_epochs"]

    events = alice.get(f"/v1/jobs/{job['id']}/events").json()["data"]
    statuses = [e["data"]["status"] for e in events if e["type"] == "status"]
    assert statuses == ["queued", "running", "succeeded"]
    assert {"progress", "evaluation", "checkpoint"} <= {e["type"] for e in events}
    # The dynamics fit shows how far through its epoch cap it is, not 0 % until SAC starts.
    fit = [e["data"] for e in events if e["type"] == "progress" and e["data"]["phase"] == "dynamics"]
    assert fit and all(d["fraction"] == round(d["step"] / d["total"], 4) > 0 for d in fit), fit
    page = alice.get(f"/v1/jobs/{job['id']}/events", params={"after": events[0]["id"], "limit": 2}).json()
    assert [e["id"] for e in page["data"]] == [e["id"] for e in events[1:3]] and page["has_more"]

    # The stream sends the same events, each under its id, and ends with the job (or the client raises).
    assert list(alice.api.stream_events(job["id"])) == events
    # A reconnecting client resumes after the last event it saw.
    assert list(alice.api.stream_events(job["id"], last_event_id=events[-2]["id"])) == events[-1:]

    metrics = alice.get(f"/v1/jobs/{job['id']}/metrics", params={"name": "sac/critic_loss"}).json()["data"]
    assert metrics and all(m["name"] == "sac/critic_loss" for m in metrics)
    evals = alice.get(f"/v1/jobs/{job['id']}/evaluations").json()["data"]
    assert [e["epoch"] for e in evals] == [1, 2] and evals[-1]["normalized_score"] == done["last_score"]
    first = alice.get(f"/v1/jobs/{job['id']}/evaluations", params={"limit": 1}).json()
    assert first["data"] == evals[:1] and first["has_more"] and first["next_after"] == evals[0]["id"]
    rest = alice.get(f"/v1/jobs/{job['id']}/evaluations", params={"after": first["next_after"]}).json()
    assert rest["data"] == evals[1:] and not rest["has_more"]
    scores = [e["normalized_score"] for e in evals]
    assert done["best_epoch"] == evals[scores.index(max(scores))]["epoch"] and done["best_score"] == max(scores)
    assert done["final_score"] == sum(scores) / len(scores)  # fewer than three evaluations: the mean of all
    ckpts = alice.get(f"/v1/jobs/{job['id']}/checkpoints").json()["data"]
    assert ckpts and ckpts[-1]["epoch"] == 2 and ckpts[-1]["size_bytes"] > 0
    png = alice.get(f"/v1/jobs/{job['id']}/curve.png")
    assert png.headers["content-type"] == "image/png" and png.content.startswith(b"\x89PNG")

    r = alice.get(f"/v1/jobs/{job['id']}/policy")
    assert r.status_code == 200
    # curl -I shows the size and ETag without the body; a client holding that ETag gets 304 and no body again.
    head = alice.head(f"/v1/jobs/{job['id']}/policy")
    assert head.status_code == 200 and not head.content
    assert int(head.headers["content-length"]) == len(r.content) and head.headers["etag"] == r.headers["etag"]
    for held in (f'"other", {r.headers["etag"]}', f'W/{r.headers["etag"]}', "*"):
        same = alice.get(f"/v1/jobs/{job['id']}/policy", headers={"If-None-Match": held})
        assert same.status_code == 304 and not same.content and same.headers["etag"] == r.headers["etag"], held
    other = alice.get(f"/v1/jobs/{job['id']}/policy", params={"which": "best"}, headers={"If-None-Match": '"x"'})
    assert other.status_code == 200 and other.content
    policy = torch.jit.load(io.BytesIO(r.content))
    actions = policy(torch.randn(5, 11))
    assert actions.shape == (5, 3) and bool((actions.abs() <= 1).all())
    state = torch.load(io.BytesIO(alice.get(f"/v1/jobs/{job['id']}/policy", params={"format": "state_dict"}).content))
    assert any(k.startswith("net.") for k in state)
    import numpy as np
    import onnxruntime

    onnx = alice.get(f"/v1/jobs/{job['id']}/policy", params={"format": "onnx"})
    assert onnx.status_code == 200
    obs = np.random.default_rng(0).normal(size=(4, 11)).astype(np.float32)
    onnx_actions = onnxruntime.InferenceSession(onnx.content).run(None, {"obs": obs})[0]
    np.testing.assert_allclose(onnx_actions, policy(torch.from_numpy(obs)).detach().numpy(), atol=1e-5)
    meta = alice.get(f"/v1/jobs/{job['id']}/policy", params={"format": "metadata"}).json()
    assert meta["env"] == "hopper" and meta["obs_dim"] == 11 and (meta["which"], meta["epoch"]) == ("last", 2)

    # The best policy: its own files, every format, with metadata naming the evaluation it was chosen by.
    best = {f: alice.get(f"/v1/jobs/{job['id']}/policy", params={"which": "best", "format": f})
            for f in ("torchscript", "state_dict", "onnx", "metadata")}
    assert all(r.status_code == 200 for r in best.values()), {f: r.text for f, r in best.items()}
    assert "-best-" in best["torchscript"].headers["content-disposition"]
    best_actions = torch.jit.load(io.BytesIO(best["torchscript"].content))(torch.from_numpy(obs))
    np.testing.assert_allclose(onnxruntime.InferenceSession(best["onnx"].content).run(None, {"obs": obs})[0],
                               best_actions.detach().numpy(), atol=1e-5)
    best_meta = best["metadata"].json()
    assert (best_meta["which"], best_meta["epoch"]) == ("best", done["best_epoch"])
    assert best_meta["normalized_score"] == done["best_score"] and "deterministic episodes" in best_meta["selected_by"]
    assert alice.get(f"/v1/jobs/{job['id']}/policy", params={"which": "last"}).content == r.content  # r: the default
    bad = alice.get(f"/v1/jobs/{job['id']}/policy", params={"which": "worst"})
    assert bad.status_code == 422 and bad.headers["content-type"] == "application/problem+json"
    assert bad.json()["errors"][0]["field"] == "query.which", bad.text
    # A job that succeeded before runs kept both policies has its one policy directly under policy/: the default
    # download still finds it.
    folder = job_dir(settings, job["id"]) / "policy"
    for f in (folder / "last").iterdir():
        f.rename(folder / f.name)
    assert alice.get(f"/v1/jobs/{job['id']}/policy").content == r.content

    listed = alice.get("/v1/jobs", params={"status": "succeeded"}).json()["data"]
    assert job["id"] in [j["id"] for j in listed]
    assert alice.post(f"/v1/jobs/{job['id']}/cancel").status_code == 409

    # Same data, seed and dynamics config, another algorithm: the ensemble comes from the cache, not trained again.
    again = alice.post("/v1/jobs", json={"dataset_id": ds["id"], "algorithm": "mopo", "preset": "smoke", "seed": 1,
                                         "overrides": {"epochs": 1}}).json()
    again_done = alice.api.wait(again["id"], timeout=120)
    assert again_done["status"] == "succeeded", again_done
    assert again_done["latest_metrics"]["dynamics/from_cache"] == 1.0
    assert again_done["dynamics"] == {**dynamics, "from_cache": True}
    metrics = alice.get(f"/v1/jobs/{again['id']}/metrics", params={"name": "dynamics/holdout_mse"}).json()["data"]
    assert metrics == [], "a cached ensemble has no training epochs"

    assert alice.delete(f"/v1/datasets/{ds['id']}").status_code == 204
    assert alice.get(f"/v1/datasets/{ds['id']}").status_code == 404
    assert alice.get(f"/v1/jobs/{job['id']}").json()["dataset_id"] is None
