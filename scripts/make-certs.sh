#!/usr/bin/env bash
# Makes a throw-away certificate authority and the certificates of a scancorr bus, for tests
# and for a first install (replace them with your site's PKI in production):
#
#   scripts/make-certs.sh DIR [MACHINE...]      (machines default: m1 m2)
#
# DIR/ca.pem, ca-key.pem                 the CA (the routers' and clients' root_ca_certificate)
# DIR/router-{cert,key}.pem              CN router, SAN localhost, 127.0.0.1 (server and client)
# DIR/scancorrd-{cert,key}.pem           CN scancorrd           (the service)
# DIR/controller-M-{cert,key}.pem        CN controller-M        (one per machine)
# DIR/app-shape-analysis-{cert,key}.pem  CN app-shape-analysis  (an app)
# DIR/operator-{cert,key}.pem            CN operator            (an operator)
# DIR/lab-metrology-{cert,key}.pem       CN lab-metrology       (the metrology lab: an operator's rights)
# DIR/auditor-{cert,key}.pem             CN auditor             (reads calibrations, changes none)
# DIR/rogue-ca.pem, rogue-{cert,key}.pem a second CA and a `controller-m1` it signed (for
#                                        tests: a certificate the router must refuse)
#
# Keys are P-256 (PKCS#8), certificates X.509 v3 valid for 30 days. Names are the access
# control's subjects in deploy/router.json5. Needs openssl.
set -euo pipefail
dir="${1:?usage: make-certs.sh DIR [MACHINE...]}"
shift
machines=("${@:-}")
[ -n "${machines[0]:-}" ] || machines=(m1 m2)
command -v openssl >/dev/null || { echo "make-certs.sh: needs openssl" >&2; exit 1; }
mkdir -p "$dir"
cd "$dir"
days=30

key() { openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null; }

ca() { # name
    key "$1-key.pem"
    openssl req -x509 -new -key "$1-key.pem" -out "$1.pem" -days "$days" -subj "/CN=scancorr test $1" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
}

leaf() { # cn ca
    local cn="$1" ca="$2" ext
    key "$cn-key.pem"
    openssl req -new -key "$cn-key.pem" -out "$cn.csr" -subj "/CN=$cn" 2>/dev/null
    ext="$(mktemp)"
    {
        echo "basicConstraints=critical,CA:FALSE"
        echo "keyUsage=critical,digitalSignature,keyEncipherment"
        echo "extendedKeyUsage=serverAuth,clientAuth"
        echo "subjectAltName=DNS:$cn,DNS:localhost,IP:127.0.0.1"
    } >"$ext"
    openssl x509 -req -in "$cn.csr" -CA "$ca.pem" -CAkey "$ca-key.pem" -CAcreateserial \
        -out "$cn-cert.pem" -days "$days" -extfile "$ext" 2>/dev/null
    rm -f "$ext" "$cn.csr"
}

ca ca
leaf router ca
leaf scancorrd ca
for m in "${machines[@]}"; do leaf "controller-$m" ca; done
leaf app-shape-analysis ca
leaf operator ca
leaf lab-metrology ca
leaf auditor ca
# A certificate for an existing name from a CA the bus does not trust.
ca rogue-ca
leaf controller-m1 rogue-ca
mv controller-m1-cert.pem rogue-cert.pem
mv controller-m1-key.pem rogue-key.pem
for m in "${machines[@]}"; do [ "$m" != m1 ] || leaf controller-m1 ca; done
rm -f ./*.srl
echo "$dir: CA and certificates for router, scancorrd, ${machines[*]/#/controller-}, app-shape-analysis, operator, lab-metrology, auditor (+ rogue)" >&2
