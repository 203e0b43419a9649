# Sourced by the scripts that run on the GPU machine (from the repository root).
# The GPU machine has no zstd of its own; `pack.sh common` carries one with its libraries.
zstd() {
    local d
    for d in .device/common/zstd "${STASH:-/root/worldpack-pieces}/common/zstd"; do
        [ -x "$d/zstd" ] && { LD_LIBRARY_PATH="$d" "$d/zstd" "$@"; return; }
    done
    command zstd "$@"
}
