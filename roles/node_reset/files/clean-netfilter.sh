#!/bin/sh
# Remove the netfilter chains whose names start with one of the prefixes given, and every rule that jumps to them,
# from each iptables variant on this host (iptables and ip6tables; legacy and nft); the other chains and rules
# stay. kube-proxy's nftables tables (nftables mode) go too. Prints one line per variant it changed ("would
# change" with --check, which changes nothing).
#   clean-netfilter.sh [--check] KUBE- CILIUM cali-
set -eu
check=false
if [ "${1:-}" = --check ]; then check=true; shift; fi
[ "$#" -gt 0 ] || { echo "clean-netfilter.sh: no chain prefix given" >&2; exit 2; }
prefixes=$(printf '%s\n' "$@" | sed 's/[].[\\*^$|+?(){}]/\\&/g' | paste -sd '|' -)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
for tool in iptables iptables-legacy iptables-nft ip6tables ip6tables-legacy ip6tables-nft; do
  if ! command -v "$tool-save" >/dev/null 2>&1 || ! command -v "$tool-restore" >/dev/null 2>&1; then continue; fi
  "$tool-save" >"$work/before" 2>/dev/null || continue
  grep -v -E "^:($prefixes)|^-A ($prefixes)| -[jg] ($prefixes)" "$work/before" >"$work/after" || true
  cmp -s "$work/before" "$work/after" && continue
  removed=$(grep -c -E "^:($prefixes)|^-A ($prefixes)| -[jg] ($prefixes)" "$work/before" || true)
  if $check; then
    echo "would change $tool: $removed lines"
  else
    "$tool-restore" <"$work/after"
    echo "changed $tool: $removed lines"
  fi
done
if command -v nft >/dev/null 2>&1; then
  for family in ip ip6; do
    nft list table "$family" kube-proxy >/dev/null 2>&1 || continue
    if $check; then echo "would change nft: table $family kube-proxy"; else
      nft delete table "$family" kube-proxy
      echo "changed nft: table $family kube-proxy"
    fi
  done
fi
