#!/usr/bin/env bash
# A private certificate authority and a server certificate for `mscale serve --tls-cert/--tls-key`
# (TLS is required when the orchestrator listens on anything but loopback).
# Usage: bash deploy/make-certs.sh DIR NAME...
#   NAME: every host name or IP address clients use to reach the orchestrator (localhost and
#   127.0.0.1 are always added, for health probes on the orchestrator's own host).
# Writes DIR/ca.crt (give it to clients: --ca-file or MSCALE_CA_FILE), DIR/tls.crt and
# DIR/tls.key (the server's; mode 0600), DIR/ca.key (keep it offline). An existing CA in DIR
# is reused. The file names match a Kubernetes secret made with
#   kubectl create secret generic mscale-tls --from-file=DIR/tls.crt --from-file=DIR/tls.key --from-file=DIR/ca.crt
set -euo pipefail
if [ $# -lt 1 ]; then
  echo "usage: $0 DIR [NAME...]" >&2
  exit 2
fi
dir="$1"
shift
mkdir -p "$dir"
umask 077
san="DNS:localhost,IP:127.0.0.1"
for name in "$@"; do
  if [[ "$name" =~ ^[0-9.]+$ || "$name" == *:* ]]; then san="$san,IP:$name"; else san="$san,DNS:$name"; fi
done
days="${MSCALE_CERT_DAYS:-825}"
if [ ! -s "$dir/ca.crt" ] || [ ! -s "$dir/ca.key" ]; then
  openssl req -x509 -newkey rsa:3072 -nodes -keyout "$dir/ca.key" -out "$dir/ca.crt" -days 3650 \
    -subj "/CN=mscale orchestrator CA" 2>/dev/null
fi
openssl req -newkey rsa:3072 -nodes -keyout "$dir/tls.key" -out "$dir/tls.csr" -subj "/CN=${1:-localhost}" 2>/dev/null
printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n' "$san" > "$dir/tls.ext"
openssl x509 -req -in "$dir/tls.csr" -CA "$dir/ca.crt" -CAkey "$dir/ca.key" -CAcreateserial \
  -out "$dir/tls.crt" -days "$days" -extfile "$dir/tls.ext" 2>/dev/null
rm -f "$dir/tls.csr" "$dir/tls.ext"
chmod 0644 "$dir/ca.crt" "$dir/tls.crt"
echo "make-certs: $dir/tls.crt for $san (CA $dir/ca.crt)"
