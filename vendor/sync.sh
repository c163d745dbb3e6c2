#!/usr/bin/env bash
# The vendored crates as their crates.io release plus umgen's patch (vendor/patches/CRATE-VERSION.patch):
#   vendor/sync.sh check   rebuild each from its release and patch, and fail if vendor/CRATE differs
#   vendor/sync.sh apply   write vendor/CRATE from its release and patch (after changing a version below;
#                          rejected hunks are left as *.rej for a person to resolve)
#   vendor/sync.sh diff    write each patch from vendor/CRATE against its release (after editing vendor/)
# The releases are fetched with cargo into its registry cache (crates.io only, no other network).
set -euo pipefail
cd "$(dirname "$0")"
CRATES=("cubecl-cuda 0.10.0" "cubecl-common 0.10.0")
mode="${1:-check}"
# Files cargo adds to a downloaded crate, not part of the release's sources as vendored.
EXCLUDE=(--exclude=.cargo-ok --exclude=.cargo_vcs_info.json --exclude=Cargo.lock --exclude=Cargo.toml.orig)

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/fetch/src"
{
  printf '[package]\nname = "vendor-fetch"\nversion = "0.0.0"\nedition = "2021"\n[dependencies]\n'
  for c in "${CRATES[@]}"; do set -- $c; printf '%s = "=%s"\n' "$1" "$2"; done
} > "$work/fetch/Cargo.toml"
echo 'fn main() {}' > "$work/fetch/src/main.rs"
(cd "$work/fetch" && cargo fetch --quiet)
registry="${CARGO_HOME:-$HOME/.cargo}/registry/src"

status=0
for c in "${CRATES[@]}"; do
  set -- $c
  name=$1 version=$2
  release=$(ls -d "$registry"/*/"$name-$version" | head -1)
  patch="patches/$name-$version.patch"
  case "$mode" in
    diff)
      # Headers without the files' times, so that the patch changes only when the sources do.
      (cd "$work" && cp -r "$release" a && cp -r "$OLDPWD/$name" b && { diff -ruN "${EXCLUDE[@]}" a b || true; } \
        | sed -E 's/^((---|\+\+\+) [^\t]*)\t.*$/\1/; s/^diff -ruN .* (a\/[^ ]*) (b\/[^ ]*)$/diff -ruN \1 \2/' > "$OLDPWD/$patch")
      rm -rf "$work/a" "$work/b"
      echo "$patch: $(grep -c '^+++ ' "$patch") files"
      ;;
    check | apply)
      rebuilt="$work/$name"
      cp -r "$release" "$rebuilt"
      (cd "$rebuilt" && rm -f .cargo-ok .cargo_vcs_info.json Cargo.lock Cargo.toml.orig && patch -s -p1 < "$OLDPWD/$patch")
      if [ "$mode" = apply ]; then
        rm -rf "$name" && cp -r "$rebuilt" "$name"
        echo "vendor/$name: $name $version with $patch"
      elif ! diff -r "$rebuilt" "$name" > "$work/$name.diff"; then
        echo "vendor/$name differs from $name $version with $patch (vendor/sync.sh diff writes the patch anew):" >&2
        head -40 "$work/$name.diff" >&2
        status=1
      else
        echo "vendor/$name = $name $version + $patch"
      fi
      ;;
    *) echo "usage: vendor/sync.sh [check|apply|diff]" >&2; exit 2 ;;
  esac
done
exit $status
