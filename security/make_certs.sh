#!/usr/bin/env bash
# Make the certificates of triscan's secure mode: one private CA, then one key + certificate per identity.
#
# Why: Zenoh's access control names a remote node by the common name (CN) of the certificate it showed in
# mutual TLS, so every service needs its own certificate whose CN is its identity (`triscan-detector`, ...).
# Each certificate carries both serverAuth and clientAuth because a peer both listens and connects.
#
# Usage: security/make_certs.sh [--force] [--days N] [--san DNS_OR_IP]... OUT_DIR [ROBOT_ID ...]
#   identities: triscan-detector, triscan-encoder, triscan-visualizer, triscan-simulator, triscan-app
#               (read-only apps) and triscan-robot-<id> for every ROBOT_ID (default: r1).
#   SANs: localhost and 127.0.0.1 always, plus every --san and the comma-separated $TRISCAN_CERT_SANS.
# Files: OUT_DIR/ca.pem (+ ca.key, keep it offline), OUT_DIR/<identity>.pem and OUT_DIR/<identity>.key.
# Keys are P-256 in PKCS#8 (what rustls reads), mode 0600; the script refuses to overwrite without --force.
set -euo pipefail

usage() {
    sed -n '8,13p' "$0" | sed 's/^# \{0,1\}//' >&2
    exit 2
}

force=0
days=825
sans=("DNS:localhost" "IP:127.0.0.1")
while [[ $# -gt 0 ]]; do
    case "$1" in
        --force) force=1; shift ;;
        --days) days="${2:?--days needs a value}"; shift 2 ;;
        --san) sans+=("${2:?--san needs a value}"); shift 2 ;;
        -h|--help) usage ;;
        --) shift; break ;;
        -*) echo "make_certs.sh: unknown option $1" >&2; usage ;;
        *) break ;;
    esac
done
[[ $# -ge 1 ]] || usage
out_dir="$1"
shift
robots=("$@")
[[ ${#robots[@]} -gt 0 ]] || robots=("r1")

if [[ -n "${TRISCAN_CERT_SANS:-}" ]]; then
    IFS=',' read -r -a extra <<<"$TRISCAN_CERT_SANS"
    sans+=("${extra[@]}")
fi
# A bare name or address becomes a SAN entry of the right type.
san_list=""
for san in "${sans[@]}"; do
    [[ -n "$san" ]] || continue
    if [[ "$san" != DNS:* && "$san" != IP:* ]]; then
        if [[ "$san" =~ ^[0-9.]+$ || "$san" == *:* ]]; then san="IP:$san"; else san="DNS:$san"; fi
    fi
    san_list+="${san_list:+,}$san"
done

command -v openssl >/dev/null || { echo "make_certs.sh: openssl not found" >&2; exit 1; }
for robot in "${robots[@]}"; do
    [[ "$robot" =~ ^[A-Za-z0-9_-]{1,64}$ ]] || { echo "make_certs.sh: bad robot id '$robot'" >&2; exit 2; }
done
identities=(triscan-detector triscan-encoder triscan-visualizer triscan-simulator triscan-app)
for robot in "${robots[@]}"; do identities+=("triscan-robot-$robot"); done

mkdir -p "$out_dir"
if [[ $force -eq 0 && -e "$out_dir/ca.pem" ]]; then
    echo "make_certs.sh: $out_dir/ca.pem exists; pass --force to replace the CA and every certificate" >&2
    exit 1
fi
umask 077  # every file written from here on (keys included) is private to the owner
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

new_key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

new_key "$out_dir/ca.key"
cat >"$tmp/ca.ext" <<EOF
basicConstraints=critical,CA:TRUE,pathlen:0
keyUsage=critical,keyCertSign,cRLSign
subjectKeyIdentifier=hash
EOF
openssl req -new -x509 -key "$out_dir/ca.key" -subj "/O=triscan/CN=triscan-ca" -days "$days" \
    -sha256 -extensions v3_ca -config <(printf '[req]\ndistinguished_name=dn\n[dn]\n[v3_ca]\n'; cat "$tmp/ca.ext") \
    -out "$out_dir/ca.pem"

for identity in "${identities[@]}"; do
    new_key "$out_dir/$identity.key"
    openssl req -new -key "$out_dir/$identity.key" -subj "/O=triscan/CN=$identity" -out "$tmp/$identity.csr"
    cat >"$tmp/$identity.ext" <<EOF
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=$san_list
authorityKeyIdentifier=keyid
subjectKeyIdentifier=hash
EOF
    openssl x509 -req -in "$tmp/$identity.csr" -CA "$out_dir/ca.pem" -CAkey "$out_dir/ca.key" \
        -CAcreateserial -CAserial "$tmp/ca.srl" -days "$days" -sha256 -extfile "$tmp/$identity.ext" \
        -out "$out_dir/$identity.pem" 2>/dev/null
done
chmod 600 "$out_dir"/*.key
chmod 644 "$out_dir"/*.pem
echo "make_certs.sh: CA and ${#identities[@]} identities (${identities[*]}) in $out_dir, SANs $san_list" >&2
