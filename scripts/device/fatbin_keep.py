"""Zero the GPU code a lent machine will never load, so the CUDA provider travels small.

ONNX Runtime's CUDA provider (libonnxruntime_providers_cuda.so, 284 MB) carries
its kernels as cubins for several GPU architectures in the ELF section
`.nv_fatbin`. The CUDA driver reads each entry's header and loads the one that
matches the card, so the payloads of the others can be zeroed in place: every
offset and header stays as it was, and the zeros compress to almost nothing.

    python3 fatbin_keep.py IN OUT --keep 90        # keep sm_90 (H100, H200)
"""

import argparse
import struct
import sys

FATBIN_MAGIC = 0xBA55ED50


def nv_fatbin_section(data: bytes) -> tuple[int, int]:
    """(file offset, size) of `.nv_fatbin`, read from the ELF64 section headers."""
    if data[:4] != b"\x7fELF" or data[4] != 2:
        raise SystemExit("not a 64-bit ELF file")
    shoff, = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    names_off, = struct.unpack_from("<Q", data, shoff + shstrndx * shentsize + 0x18)
    for i in range(shnum):
        h = shoff + i * shentsize
        name_at, = struct.unpack_from("<I", data, h)
        name = data[names_off + name_at:data.index(b"\0", names_off + name_at)]
        if name == b".nv_fatbin":
            off, size = struct.unpack_from("<QQ", data, h + 0x18)
            return off, size
    raise SystemExit("no .nv_fatbin section")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src")
    ap.add_argument("dst")
    ap.add_argument("--keep", type=int, action="append", required=True, help="an sm_XX architecture to keep (e.g. 90)")
    a = ap.parse_args()
    data = bytearray(open(a.src, "rb").read())
    start, size = nv_fatbin_section(data)
    pos, end = start, start + size
    kept = zeroed = 0
    while pos + 16 <= end:
        magic, _version, header, body = struct.unpack_from("<IHHQ", data, pos)
        if magic != FATBIN_MAGIC:
            pos += 8  # alignment padding between containers
            continue
        entry, stop = pos + header, pos + header + body
        while entry < stop:
            _kind, _ver, entry_header, payload = struct.unpack_from("<HHIQ", data, entry)
            arch, = struct.unpack_from("<I", data, entry + 28)
            first = entry + entry_header
            if arch in a.keep:
                kept += payload
            else:
                data[first:first + payload] = bytes(payload)
                zeroed += payload
            entry = first + payload
        pos = stop
    if kept == 0:
        sys.exit(f"no sm_{a.keep} code in {a.src}: nothing would load")
    open(a.dst, "wb").write(data)
    print(f"{a.dst}: kept {kept / 1e6:.1f} MB of sm_{'/'.join(map(str, a.keep))} code, zeroed {zeroed / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
