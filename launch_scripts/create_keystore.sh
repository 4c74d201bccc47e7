#!/usr/bin/env bash
# Create a DDS Security keystore in the SROS2 layout with openssl, for running the patchwalk nodes with
# authentication, access control and encryption (see "DDS Security" in README.md).
#
#   launch_scripts/create_keystore.sh KEYSTORE [ENCLAVE ...]
#
# ENCLAVE is an enclave path such as /patchwalk/step_executor (default: one enclave per patchwalk node and
# one for an operator: /patchwalk/patch_mapper /patchwalk/step_executor /patchwalk/terrain_sim
# /patchwalk/operator). An ENCLAVE written PATH=observer gets read-only permissions (it may subscribe to every
# topic and publish only what every ROS 2 node writes about itself — graph, log, parameter events, answers
# to its own parameter services: it sees the robot but cannot arm, play or stop it); every other enclave may
# publish and subscribe everything. Existing CA keys in KEYSTORE are reused, so enclaves can be added later.
#
# Layout (as `ros2 security create_keystore` / `create_enclave` write it):
#   KEYSTORE/public/{ca.cert.pem, identity_ca.cert.pem -> ca.cert.pem, permissions_ca.cert.pem -> ca.cert.pem}
#   KEYSTORE/private/{ca.key.pem, identity_ca.key.pem -> ca.key.pem, permissions_ca.key.pem -> ca.key.pem}
#   KEYSTORE/enclaves/{governance.xml, governance.p7s}
#   KEYSTORE/enclaves/<enclave>/{cert.pem, key.pem, permissions.xml, permissions.p7s,
#                               identity_ca.cert.pem, permissions_ca.cert.pem, governance.p7s}
# The domain rule covers ROS_DOMAIN_ID 0-232. Keys are ECDSA P-256, certificates valid for 10 years.
set -euo pipefail

if [ $# -lt 1 ] || [ "$1" = "-h" ] || [ "$1" = "--help" ]; then
    sed -n '2,21p' "$0" | sed 's/^# \{0,1\}//'
    exit 2
fi
command -v openssl >/dev/null || { echo "create_keystore.sh: openssl not found (Debian: apt-get install openssl)" >&2; exit 1; }

KEYSTORE="$1"
shift
if [ $# -eq 0 ]; then
    set -- /patchwalk/patch_mapper /patchwalk/step_executor /patchwalk/terrain_sim /patchwalk/operator
fi
DAYS=3650
NOT_BEFORE="$(date -u +%Y-%m-%dT%H:%M:%S)"
NOT_AFTER="$(date -u -d "+$DAYS days" +%Y-%m-%dT%H:%M:%S)"

mkdir -p "$KEYSTORE/public" "$KEYSTORE/private" "$KEYSTORE/enclaves"
KEYSTORE="$(cd "$KEYSTORE" && pwd)"
CA_CERT="$KEYSTORE/public/ca.cert.pem"
CA_KEY="$KEYSTORE/private/ca.key.pem"

# --- the CA (one for identities and permissions, as SROS2 does) -------------------------------------------
if [ ! -f "$CA_KEY" ] || [ ! -f "$CA_CERT" ]; then
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$CA_KEY"
    chmod 600 "$CA_KEY"
    openssl req -x509 -new -key "$CA_KEY" -sha256 -days "$DAYS" -subj "/CN=patchwalk_keystore_ca" -out "$CA_CERT"
fi
for role in identity_ca permissions_ca; do
    ln -sfn ca.cert.pem "$KEYSTORE/public/$role.cert.pem"
    ln -sfn ca.key.pem "$KEYSTORE/private/$role.key.pem"
done

sign() { # sign IN.xml OUT.p7s: S/MIME signature by the permissions CA, as DDS Security reads it
    openssl smime -sign -text -in "$1" -out "$2" -signer "$CA_CERT" -inkey "$CA_KEY"
}

# --- governance: every domain joins only with valid credentials; discovery, liveliness and data encrypted --
GOVERNANCE="$KEYSTORE/enclaves/governance.xml"
cat > "$GOVERNANCE" <<'EOF'
<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
     xsi:noNamespaceSchemaLocation="http://www.omg.org/spec/DDS-SECURITY/20170901/omg_shared_ca_governance.xsd">
  <domain_access_rules>
    <domain_rule>
      <domains>
        <id_range><min>0</min><max>232</max></id_range>
      </domains>
      <allow_unauthenticated_participants>false</allow_unauthenticated_participants>
      <enable_join_access_control>true</enable_join_access_control>
      <discovery_protection_kind>ENCRYPT</discovery_protection_kind>
      <liveliness_protection_kind>ENCRYPT</liveliness_protection_kind>
      <rtps_protection_kind>SIGN</rtps_protection_kind>
      <topic_access_rules>
        <topic_rule>
          <topic_expression>*</topic_expression>
          <enable_discovery_protection>true</enable_discovery_protection>
          <enable_liveliness_protection>true</enable_liveliness_protection>
          <enable_read_access_control>true</enable_read_access_control>
          <enable_write_access_control>true</enable_write_access_control>
          <metadata_protection_kind>ENCRYPT</metadata_protection_kind>
          <data_protection_kind>ENCRYPT</data_protection_kind>
        </topic_rule>
      </topic_access_rules>
    </domain_rule>
  </domain_access_rules>
</dds>
EOF
sign "$GOVERNANCE" "$KEYSTORE/enclaves/governance.p7s"

# --- one enclave per argument -------------------------------------------------------------------------------
for spec in "$@"; do
    enclave="${spec%%=*}"
    role="full"
    if [ "$spec" != "$enclave" ]; then role="${spec#*=}"; fi
    case "$enclave" in
        /*) ;;
        *) echo "create_keystore.sh: enclave $enclave must be an absolute path (e.g. /patchwalk/step_executor)" >&2; exit 2 ;;
    esac
    case "$role" in
        full|observer) ;;
        *) echo "create_keystore.sh: unknown role $role of $enclave (full or observer)" >&2; exit 2 ;;
    esac
    dir="$KEYSTORE/enclaves${enclave}"
    mkdir -p "$dir"
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$dir/key.pem"  # PKCS#8, as DDS Security plugins read it
    chmod 600 "$dir/key.pem"
    # In -subj a '/' separates attributes: the enclave path's slashes are escaped.
    openssl req -new -key "$dir/key.pem" -subj "/CN=${enclave//\//\\/}" -out "$dir/request.csr"
    openssl x509 -req -in "$dir/request.csr" -CA "$CA_CERT" -CAkey "$CA_KEY" -sha256 -days "$DAYS" \
        -set_serial "0x$(openssl rand -hex 8)" -out "$dir/cert.pem" 2>/dev/null
    rm -f "$dir/request.csr"
    if [ "$role" = observer ]; then
        # What every ROS 2 node writes (graph, log, parameter events, answers to its own parameter
        # services) and nothing else: no topic a node listens to, no service request.
        publish="<publish><topics><topic>ros_discovery_info</topic><topic>rt/rosout</topic><topic>rt/parameter_events</topic><topic>rr/*</topic></topics></publish>"
    else
        publish="<publish><topics><topic>*</topic></topics></publish>"
    fi
    cat > "$dir/permissions.xml" <<EOF
<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance"
     xsi:noNamespaceSchemaLocation="http://www.omg.org/spec/DDS-Security/20170901/omg_shared_ca_permissions.xsd">
  <permissions>
    <grant name="${enclave}">
      <subject_name>CN=${enclave}</subject_name>
      <validity>
        <not_before>${NOT_BEFORE}</not_before>
        <not_after>${NOT_AFTER}</not_after>
      </validity>
      <allow_rule>
        <domains><id_range><min>0</min><max>232</max></id_range></domains>
        ${publish}
        <subscribe><topics><topic>*</topic></topics></subscribe>
      </allow_rule>
      <default>DENY</default>
    </grant>
  </permissions>
</dds>
EOF
    sign "$dir/permissions.xml" "$dir/permissions.p7s"
    ln -sfn "$(realpath --relative-to="$dir" "$KEYSTORE/public/identity_ca.cert.pem")" "$dir/identity_ca.cert.pem"
    ln -sfn "$(realpath --relative-to="$dir" "$KEYSTORE/public/permissions_ca.cert.pem")" "$dir/permissions_ca.cert.pem"
    ln -sfn "$(realpath --relative-to="$dir" "$KEYSTORE/enclaves/governance.p7s")" "$dir/governance.p7s"
    echo "enclave $enclave ($role): $dir"
done
