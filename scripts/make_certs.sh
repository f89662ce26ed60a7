#!/usr/bin/env bash
# Make a private CA and one certificate per service for Zetta's TLS (docs/security.md).
#
#   scripts/make_certs.sh OUT_DIR [NAME ...]
#
# OUT_DIR/ca.pem, ca-key.pem: the CA (keep ca-key.pem offline; services need only ca.pem).
# OUT_DIR/NAME.pem, NAME-key.pem: a certificate for each NAME (default: gateway env-worker
# policy-worker critic evolver), valid for DNS:NAME, DNS:localhost and IP:127.0.0.1 plus any
# names in $ZETTA_CERT_SANS (e.g. "DNS:gateway.zetta.svc,IP:10.0.0.5"), usable as server and
# client certificate (mutual TLS). Point ZETTA_TLS_CERT, ZETTA_TLS_KEY and ZETTA_TLS_CA at them.
set -euo pipefail
out=${1:?usage: make_certs.sh OUT_DIR [NAME ...]}
shift
names=("$@")
[ ${#names[@]} -gt 0 ] || names=(gateway env-worker policy-worker critic evolver)
days=${ZETTA_CERT_DAYS:-365}
mkdir -p "$out"
umask 077
if [ ! -f "$out/ca.pem" ]; then
  openssl req -x509 -newkey rsa:2048 -nodes -keyout "$out/ca-key.pem" -out "$out/ca.pem" -days "$days" \
    -subj "/CN=zetta-ca" -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
    2>/dev/null
fi
for name in "${names[@]}"; do
  sans="DNS:$name,DNS:localhost,IP:127.0.0.1${ZETTA_CERT_SANS:+,$ZETTA_CERT_SANS}"
  openssl req -newkey rsa:2048 -nodes -keyout "$out/$name-key.pem" -out "$out/$name.csr" -subj "/CN=$name" 2>/dev/null
  openssl x509 -req -in "$out/$name.csr" -CA "$out/ca.pem" -CAkey "$out/ca-key.pem" -CAcreateserial \
    -out "$out/$name.pem" -days "$days" \
    -extfile <(printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth,clientAuth\nkeyUsage=critical,digitalSignature,keyEncipherment\n' "$sans") \
    2>/dev/null
  rm -f "$out/$name.csr"
done
chmod 644 "$out"/*.pem
chmod 600 "$out"/*-key.pem
echo "CA and certificates for ${names[*]} in $out"
