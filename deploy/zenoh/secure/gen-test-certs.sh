#!/usr/bin/env bash
# Make a TEST-ONLY certificate authority and certificates for deploy/zenoh/secure/*-tls.json5.
#   deploy/zenoh/secure/gen-test-certs.sh [OUT_DIR] [ROUTER_NAMES]
# OUT_DIR defaults to deploy/zenoh/secure/certs (ignored by git). ROUTER_NAMES is the router
# certificate's subjectAltName list (default "DNS:localhost,IP:127.0.0.1"; add your hosts' names
# and addresses for a real fleet). Client certificates carry a common name that access_control can
# match with cert_common_names: the role (vehicle, host, ops) and, for per-vehicle rules as in
# router-acl.json5, the vehicle id (cv0..cv3).
# The private keys are unencrypted: for tests on one machine only. A real fleet keeps its CA key
# offline and gives each machine only its own key (chmod 600).
set -euo pipefail
out="${1:-deploy/zenoh/secure/certs}"
sans="${2:-DNS:localhost,IP:127.0.0.1}"
mkdir -p "$out"
cd "$out"
days=365

# 1. the certificate authority
openssl req -x509 -newkey rsa:2048 -nodes -keyout ca-key.pem -out ca.pem -days "$days" \
  -subj "/CN=mapc-test-ca" -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" \
  2>/dev/null

# 2. a key and a CA-signed certificate per name (the router has subjectAltNames; clients a CN)
sign() {  # name, extensions
  openssl req -newkey rsa:2048 -nodes -keyout "$1-key.pem" -out "$1.csr" -subj "/CN=$1" 2>/dev/null
  printf '%s\n' "$2" > "$1.ext"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca-key.pem -CAcreateserial -out "$1.pem" -days "$days" \
    -extfile "$1.ext" 2>/dev/null
  rm -f "$1.csr" "$1.ext"
}
sign router "subjectAltName=$sans
extendedKeyUsage=serverAuth,clientAuth
basicConstraints=CA:FALSE"
for name in vehicle host ops cv0 cv1 cv2 cv3; do
  sign "$name" "extendedKeyUsage=clientAuth
basicConstraints=CA:FALSE"
done
chmod 600 ./*-key.pem
echo "test certificates in $(pwd): ca.pem router.pem vehicle.pem host.pem ops.pem cv0.pem..cv3.pem (+ *-key.pem)"
