/* layerwatch tab: state pushed by the plugin (send_plugin_message) and GET /api/plugin/layerwatch. */
$(function () {
    function LayerwatchViewModel(parameters) {
        var self = this;
        self.loginState = parameters[0];
        self.job = ko.observable(null);
        self.status = ko.observable("idle");
        self.message = ko.observable("");
        self.settingsError = ko.observable(null);
        self.layers = ko.observable(0);
        self.nLayers = ko.observable(0);
        self.pauses = ko.observable(0);
        self.last = ko.observable(null);
        self.ratios = ko.observableArray([]);
        self.overlayLayer = ko.observable(null);

        self.overlayUrl = ko.pureComputed(function () {
            return "plugin/layerwatch/overlay.png?layer=" + self.overlayLayer();
        });
        self.sparkline = ko.pureComputed(function () {
            var pts = self.ratios().filter(function (r) { return r[1] !== null; });
            if (!pts.length) return "";
            var n = Math.max(pts[pts.length - 1][0], 1), top = Math.max.apply(null, pts.map(function (r) { return r[1]; }).concat([10]));
            return pts.map(function (r) { return (400 * r[0] / n).toFixed(1) + "," + (80 - 78 * r[1] / top).toFixed(1); }).join(" ");
        });

        self.update = function (s) {
            self.job(s.job); self.status(s.status); self.message(s.message || "");
            self.settingsError(s.settings_error); self.layers(s.layers); self.nLayers(s.n_layers);
            self.pauses(s.pauses); self.last(s.last); self.ratios(s.ratios || []);
            self.overlayLayer(s.overlay_layer === undefined ? null : s.overlay_layer);
        };
        self.refresh = function () {
            OctoPrint.simpleApiGet("layerwatch").done(self.update);
        };
        self.onUserLoggedIn = self.refresh;
        self.onStartupComplete = function () { if (self.loginState.isUser()) self.refresh(); };
        self.onDataUpdaterPluginMessage = function (plugin, data) {
            if (plugin === "layerwatch") self.update(data);
        };
    }

    OCTOPRINT_VIEWMODELS.push({
        construct: LayerwatchViewModel,
        dependencies: ["loginStateViewModel"],
        elements: ["#layerwatch_tab"]
    });
});
