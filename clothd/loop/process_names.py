"""The names (comm, as ps and top show them) of the daemon's spawned children that are told apart by
name: the API process names itself so (clothd/api/serve_api.py), and the benches find it by it."""

API_PROCESS_NAME = "clothd-api"
