"""Replacing a control plane: which etcd members a rebuilt control plane's join must remove first.

A control plane rebuilt from a bare disk joins again under its old node name and peer address; etcd still lists
its old member (its data gone with the disk), and adding the new one beside it fails (the peer URL is taken) or
leaves the cluster with a member that never answers. The old member is removed first, through a control plane
that serves, found by name or, for a member added but never started (no name yet), by its peer URL.
"""

from __future__ import annotations


def stale_members(members: list, joining_names: list, joining_peer_urls: list) -> list[dict]:
    """The members of etcd's member list (as its v3 JSON gateway returns them: ``ID``, ``name``, ``peerURLs``)
    that belong to a control plane joining now; each once, in the list's order. Anything that is not a member
    (no ``ID``) is left alone."""
    names = {str(n) for n in joining_names or () if n}
    urls = {str(u) for u in joining_peer_urls or () if u}
    found = []
    for member in members or ():
        if not isinstance(member, dict) or not member.get("ID"):
            continue
        peers = {str(u) for u in member.get("peerURLs") or ()}
        if str(member.get("name") or "") in names or peers & urls:
            found.append({"ID": str(member["ID"]), "name": str(member.get("name") or ""), "peerURLs": sorted(peers)})
    return found
