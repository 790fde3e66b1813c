#!/usr/bin/env bash
# make-certs.sh: a test certificate authority and the certificates of a deployment, for zenoh's
# TLS (tls/ endpoints) with mutual authentication (enable_mtls: true on both sides).
#
#   deploy/make-certs.sh OUT_DIR [SAN ...] [CN:NAME ...]
#
# Writes into OUT_DIR (created, mode 700):
#   ca.pem, ca.key                    the test CA (10 years; keep ca.key off the sites)
#   work-site.pem, work-site.key      CN=work-site; SANs: localhost, 127.0.0.1, 10.77.0.2
#                                     (the netns work address) and every extra SAN given,
#                                     e.g. DNS:robot.example.org or IP:192.0.2.10
#   operator.pem, operator.key        CN=operator: the identity access control lets command
#   router.pem, router.key            CN=router (deploy/router.py); SANs: localhost, 127.0.0.1,
#                                     10.77.0.1 and the extra SANs
#   viewer.pem, viewer.key            CN=viewer: authenticated, but not allowed to command
#   rogue-ca.pem, intruder.pem/.key   CN=operator signed by ANOTHER CA: must be refused
#   NAME.pem, NAME.key                for each CN:NAME given: CN=NAME, e.g. one work site and
#                                     one operator per cell of a fleet (deploy/fleet.py); SANs
#                                     as work-site's
# Access control matches the client certificate's common name (CN), so the CN is the role.
# These are TEST certificates: for a real deployment use your organisation's CA and keep each
# private key only on its own machine.
set -euo pipefail

if [[ $# -lt 1 || $1 == -h || $1 == --help ]]; then
  sed -n '2,22p' "$0" | sed 's/^# \{0,1\}//'
  exit $(( $# < 1 ? 2 : 0 ))
fi
out=$1
shift
extra_sans=""
extra_names=()
for arg in "$@"; do
  case $arg in
    DNS:*|IP:*) extra_sans+=",${arg}" ;;
    CN:*)
      name=${arg#CN:}
      # A file name and a zenoh ACL common name: no path, no space, no shell surprises.
      if [[ ! $name =~ ^[A-Za-z0-9][A-Za-z0-9._-]{0,62}$ ]]; then
        echo "make-certs: CN:NAME takes letters, digits, '.', '_' and '-' (at most 63), got '$arg'" >&2
        exit 2
      fi
      case $name in
        ca|rogue-ca|work-site|operator|router|viewer|intruder)
          echo "make-certs: CN:$name would overwrite a certificate this script always writes" >&2
          exit 2 ;;
      esac
      extra_names+=("$name") ;;
    *) echo "make-certs: expected DNS:name, IP:address or CN:name, got '$arg'" >&2; exit 2 ;;
  esac
done

mkdir -p "$out"
chmod 700 "$out"
cd "$out"
days=3650

# ca NAME: a self-signed CA (EC P-256, PKCS#8 keys: what rustls reads).
ca() {
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1.key" 2>/dev/null
  openssl req -x509 -new -key "$1.key" -sha256 -days $days -subj "/CN=telerobot test $1" \
    -addext "basicConstraints=critical,CA:TRUE" \
    -addext "keyUsage=critical,keyCertSign,cRLSign" -out "$1.pem" 2>/dev/null
}

# leaf NAME CN SANS CA: a certificate for both TLS server and client use, signed by CA.
leaf() {
  local name=$1 cn=$2 sans=$3 ca=$4
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$name.key" 2>/dev/null
  openssl req -new -key "$name.key" -subj "/CN=$cn" -out "$name.csr" 2>/dev/null
  cat > "$name.ext" <<EOF
basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=$sans
EOF
  openssl x509 -req -in "$name.csr" -CA "$ca.pem" -CAkey "$ca.key" -CAcreateserial \
    -days $days -sha256 -extfile "$name.ext" -out "$name.pem" 2>/dev/null
  rm -f "$name.csr" "$name.ext"
  chmod 600 "$name.key"
}

ca ca
ca rogue-ca
leaf work-site work-site "DNS:work-site,DNS:localhost,IP:127.0.0.1,IP:10.77.0.2${extra_sans}" ca
leaf operator operator "DNS:operator" ca
leaf router router "DNS:router,DNS:localhost,IP:127.0.0.1,IP:10.77.0.1${extra_sans}" ca
leaf viewer viewer "DNS:viewer" ca
leaf intruder operator "DNS:operator" rogue-ca
for name in "${extra_names[@]}"; do
  leaf "$name" "$name" "DNS:$name,DNS:localhost,IP:127.0.0.1,IP:10.77.0.2${extra_sans}" ca
done
rm -f ./*.srl rogue-ca.key
chmod 600 ca.key
for name in work-site operator router viewer "${extra_names[@]}"; do
  openssl verify -CAfile ca.pem "$name.pem" >/dev/null
done
echo "make-certs: wrote $(pwd)/{ca,work-site,operator,router,viewer,intruder,rogue-ca}.pem and keys"
if (( ${#extra_names[@]} )); then
  echo "make-certs: and ${#extra_names[@]} more: ${extra_names[*]}"
fi
