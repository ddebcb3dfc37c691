"""pvpython: every SIPMSS proxy is usable from the ParaView GUI.

- Every property a user sets is of a type ParaView 5.11's properties panel draws a widget for
  (pqProxyWidget::createWidgetForProperty draws Int/Double/StringVectorProperty, a
  ProxyProperty with a ProxyListDomain, and a plain command property; it draws nothing for an
  IdTypeVectorProperty, so such a property must be hidden with panel_visibility="never").
- "SIPMSS Cluster File" and "SIPMSS Decimate File" are in Sources > SIPMSS: ParaView's menus
  (pqProxyGroupMenuManager::lookForNewDefinitions) list a "sources" proxy with a ShowInMenu hint
  and skip every proxy with a ReaderFactory hint.
- The filters are in Filters > SIPMSS, and File > Open still offers both SIPMSS file readers.
"""
import os
import sys

from paraview import servermanager
from paraview.simple import LoadPlugin

LoadPlugin(os.environ["SIPMSS_PLUGIN"], remote=False, ns=globals())

pxm = servermanager.vtkSMProxyManager.GetProxyManager().GetActiveSessionProxyManager()
pdm = pxm.GetProxyDefinitionManager()
errors = []

# panel_visibility="never" hides a property from the panel; information and internal
# properties are never shown; the input is chosen in the pipeline, not in the panel.
DRAWN = ("vtkSMIntVectorProperty", "vtkSMDoubleVectorProperty", "vtkSMStringVectorProperty")


def panel_draws(prop):
    cls = prop.GetClassName()
    if cls in DRAWN:
        return True
    if cls == "vtkSMProperty":  # a command: the panel draws a button
        return True
    if cls == "vtkSMProxyProperty":
        it = prop.NewDomainIterator()
        it.Begin()
        while not it.IsAtEnd():
            if it.GetDomain().IsA("vtkSMProxyListDomain"):
                return True
            it.Next()
    return False


def raw_hints(group, name):
    """The proxy's own Hints element, as the menu manager reads it (not the merged one)."""
    definition = pdm.GetProxyDefinition(group, name)
    return definition.FindNestedElementByName("Hints") if definition else None


def hint(hints, tag):
    if hints is None:
        return None
    for i in range(hints.GetNumberOfNestedElements()):
        element = hints.GetNestedElement(i)
        if element.GetName() == tag:
            return element
    return None


# every SIPMSS proxy of the menus' groups
proxies = []
for group in ("sources", "filters"):
    it = pdm.NewSingleGroupIterator(group)
    it.InitTraversal()
    while not it.IsDoneWithTraversal():
        cls = it.GetProxyDefinition().GetAttribute("class") or ""
        if cls.startswith("vtkSIPMSS"):
            proxies.append((group, it.GetProxyName()))
        it.GoToNextItem()
if len(proxies) < 4:
    errors.append("expected the SIPMSS filters and file sources, found %s" % proxies)

checked = 0
for group, name in proxies:
    proto = pxm.GetPrototypeProxy(group, name)
    it = proto.NewPropertyIterator()
    it.Begin()
    while not it.IsAtEnd():
        key, prop = it.GetKey(), it.GetProperty()
        it.Next()
        if (prop.GetInformationOnly() or prop.GetIsInternal() or
                prop.IsA("vtkSMInputProperty") or prop.GetPanelVisibility() == "never"):
            continue
        checked += 1
        if not panel_draws(prop):
            errors.append("%s/%s: property %s is a %s, for which the ParaView panel draws no "
                          "widget" % (group, name, key, prop.GetClassName()))
if checked < 20:
    errors.append("only %d properties checked" % checked)

# Filters > SIPMSS: the two filters
for name in ("SIPMSSCluster", "SIPMSSDecimate"):
    show = hint(raw_hints("filters", name), "ShowInMenu")
    if show is None or show.GetAttribute("category") != "SIPMSS":
        errors.append("filters/%s is not in Filters > SIPMSS" % name)

# Sources > SIPMSS: a "sources" proxy per file source, with that label, not a reader
for label in ("SIPMSS Cluster File", "SIPMSS Decimate File"):
    in_menu = []
    for group, name in proxies:
        if group != "sources" or pxm.GetPrototypeProxy(group, name).GetXMLLabel() != label:
            continue
        hints = raw_hints(group, name)
        show = hint(hints, "ShowInMenu")
        if show is not None and show.GetAttribute("category") == "SIPMSS" and \
                hint(hints, "ReaderFactory") is None:
            in_menu.append(name)
    if len(in_menu) != 1:
        errors.append("Sources > SIPMSS > %s: %d proxies in that menu (%s); ParaView's menus skip "
                      "a proxy with a ReaderFactory hint" % (label, len(in_menu), in_menu))

# File > Open: both SIPMSS readers are offered for a .ply and a .stl.gz (by extension; the
# "Open Data With..." dialog lists them by label)
factory = servermanager.vtkSMProxyManager.GetProxyManager().GetReaderFactory()
session = servermanager.ActiveConnection.Session
for path in ("scan.ply", "scan.stl.gz"):
    readers = factory.GetReaders(path, session)
    classes = {}
    for i in range(0, readers.GetLength(), 3):
        group, name, label = (readers.GetString(i + k) for k in range(3))
        classes[pxm.GetPrototypeProxy(group, name).GetVTKClassName()] = label
    for want in ("vtkSIPMSSCluster", "vtkSIPMSSDecimate"):
        if want not in classes:
            errors.append("File > Open %s offers no %s reader (offers %s)" %
                          (path, want, sorted(classes.values())))
        elif not classes[want].startswith("SIPMSS "):
            errors.append("File > Open %s: the %s reader is labelled %r" %
                          (path, want, classes[want]))

if errors:
    print("FAILED:\n  " + "\n  ".join(errors))
    sys.exit(1)
print("panel test passed: %d properties of %d SIPMSS proxies have a panel widget; Sources > "
      "SIPMSS and File > Open are right" % (checked, len(proxies)))
